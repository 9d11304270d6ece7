"""The rank probe's dream (`drivesim.carracing.rank`): the starts taken from a behaviour drive
(the code, the driver's hidden state and the speed there, and the world's hidden state stepped
along the drive), every driver of a family rolled from them in one batch, the futures drawn and
averaged, and the world given a real window's own inputs (open loop)."""

from __future__ import annotations

import numpy as np

from .._drivesim import Simulator
from .control import speed_after
from .family import Changes
from .rank_figures import leaving_counts


def start_decisions(decisions: int, starts: int, horizon: int, warmup: int) -> list:
    """Evenly spaced decisions of a drive ``decisions`` long, after the warm-up, each at least
    ``horizon`` before the end (a lap finished early ends the drive early)."""
    first, last = warmup + 8, decisions - horizon
    if last < first:
        raise ValueError(f"{decisions} decisions leave no start {horizon} decisions before the end")
    return sorted({int(round(x)) for x in np.linspace(first, last, starts)})


def dream_row_seed(seed: int, index: int, start: int, starts: int) -> int:
    """The steering noise's seed of driver ``index`` from start ``start`` of track ``seed``: the
    dream's row and the real window share it."""
    return seed * 1000 + index * starts + start


def steering_shaped(steer, previous, shaping: tuple):
    """``GAIN * steer + LEAD * (steer - previous)`` for ``shaping`` (GAIN, LEAD), held at full lock
    (±1): what `world_steering` steps the world with, for NumPy arrays or numbers and torch tensors
    alike (`train road`'s dream steps its world with it too)."""
    gain, lead = shaping
    return (gain * steer + lead * (steer - previous)).clip(-1.0, 1.0)


def world_steering(action: np.ndarray, previous, shaping: tuple) -> np.ndarray:
    """The inputs ``(N, 2)`` the world steps with (``--world-steering GAIN,LEAD``, a diagnostic of
    its steering's answer): each steering ``GAIN * s + LEAD * (s - previous)``, ``previous`` the
    steering of the decision before, held at full lock (±1); ``(1, 0)`` leaves them as they are.

    Full lock because the real car turns no harder past it (the env takes steering in [-1, 1]) and
    no world saw more in its data: at 1.4x an over-steering driver's 0.8 stepped the world with
    1.12, and its dream left the road twice as often as the real car (docs/judging.md)."""
    if tuple(shaping) == (1.0, 0.0):
        return action
    shaped = action.copy()
    shaped[:, 1] = steering_shaped(action[:, 1], previous, shaping)
    return shaped


def window_starts(drive: dict, count: int, horizon: int) -> tuple[list, list]:
    """The ``count`` starts in the behaviour drive ``drive`` (``drive_SEED.npz``): their
    decisions in the drive, and their indices in its kept states (which begin after the warm-up)."""
    first = int(drive["first"])
    decisions = start_decisions(first + len(drive["speed"]), count, horizon, first)
    return decisions, [d - first for d in decisions]


def starts_of(drive: dict, world: Simulator, hidden_dim: int, count: int, horizon: int,
              shaping: tuple = (1.0, 0.0)) -> dict:
    """``count`` starts in the behaviour drive ``drive`` (``drive_SEED.npz``): the code, the
    driver's hidden state and the speed at each, and the world model's hidden state there, its
    transition stepped along the drive from the decision the driver's started (the same state
    where the world is the driver's own model); and the steering the drive applied over the
    ``horizon`` decisions from each (``steer``, what `road_memory` compares), and the one before
    each (``previous``); the world steps with ``shaping`` (`world_steering`)."""
    _, at = window_starts(drive, count, horizon)
    h_world = np.zeros((1, hidden_dim), np.float32)
    hidden = []
    for t in range(max(at) + 1):
        hidden.append(h_world[0])
        action = np.array([[drive["speed"][t], drive["steer"][t]]], np.float32)
        action = world_steering(action, drive["steer"][max(t - 1, 0)], shaping)
        _, h_world = world.transition(np.ascontiguousarray(drive["z"][t:t + 1]), h_world, action)
    return {"z": drive["z"][at], "h": drive["h"][at], "speed": drive["speed"][at],
            "h_world": np.stack([hidden[t] for t in at]),
            "steer": np.stack([drive["steer"][t:t + horizon] for t in at]),
            "previous": np.array([drive["steer"][max(t - 1, 0)] for t in at], np.float32)}


def tiled(rows: np.ndarray, n: int) -> np.ndarray:
    """The starts' rows once for each of ``n`` drivers (driver-major), as the simulator takes them."""
    return np.ascontiguousarray(np.tile(rows, (n, 1)), np.float32)


def dream(driver: Simulator, world: Simulator, family: list, starts: dict, horizon: int, seed: int,
          use_value: bool, shaping: tuple = (1.0, 0.0), through_frames: bool = False, frames: list | None = None) -> dict:
    """Every driver from every start, ``horizon`` decisions, in one batch: ``return`` (with the
    value at the horizon where ``use_value``), ``rewards`` (without it) and ``off_road`` (its
    chance, averaged) ``(drivers, starts)``, and ``steer``, the steering applied, and
    ``off_steps``, each decision's off-road chance, and ``speed``, the speed stepped with,
    ``(drivers, starts, horizon)``. The drivers' policy reads the codes the world predicts (with
    ``through_frames``, those of the world's frames through the drivers' encoder), and
    their hidden states step on their own model's transition (as a real drive steps them on the
    codes of what the car sees); the world's transition predicts the codes (its inputs shaped by
    ``shaping``, `world_steering`), its reward head scores them. ``frames``, where given, receives
    the world's frame of every decision before the drivers act (``(drivers * starts, 80, 160, 3)``)."""
    k, n = len(starts["speed"]), len(family)
    z, h, h_world = (tiled(starts[key], n) for key in ("z", "h", "h_world"))
    v = np.tile(starts["speed"], n).astype(np.float32)
    previous = np.tile(starts["previous"], n)
    drivers = [d for d in family for _ in range(k)]
    changes = Changes(drivers, [dream_row_seed(seed, i, j, k) for i in range(n) for j in range(k)])
    total, off = np.zeros(n * k), np.zeros((n * k, horizon))
    steers, speeds = np.zeros((n * k, horizon), np.float32), np.zeros((n * k, horizon), np.float32)
    for step in range(horizon):
        shown = world.generate(z) if through_frames or frames is not None else None
        if frames is not None:
            frames.append(shown)
        seen = driver.encode(shown) if through_frames else z
        target, steer = changes(driver.act(seen, h)).T
        steers[:, step], speeds[:, step] = steer, v
        action = np.ascontiguousarray(np.stack([v, steer], 1), np.float32)
        _, h = driver.transition(seen, h, action)
        z, h_world = world.transition(z, h_world, world_steering(action, previous, shaping))
        previous = steer
        if world.sampling[0] > 0:
            z = world.sample(h_world, step, z)
        v = speed_after(v, target).astype(np.float32)
        reward = world.reward(z, h_world)
        total += reward[:, 0]
        off[:, step] = reward[:, 1]
    tail = world.value(z, h_world)[:, 0] if use_value else 0.0
    return {"return": (total + tail).reshape(n, k), "rewards": total.reshape(n, k),
            "off_road": off.mean(1).reshape(n, k), "steer": steers.reshape(n, k, horizon),
            "speed": speeds.reshape(n, k, horizon), "off_steps": off.reshape(n, k, horizon)}


def open_loop(world: Simulator, starts: dict, actions: np.ndarray, shaping: tuple = (1.0, 0.0)) -> np.ndarray:
    """The world stepped from the starts with given inputs, no driver in the loop: ``actions``
    ``(drivers, starts, horizon, 2)`` (the speed and the steering, a real window's) to each
    decision's off-road chance ``(drivers, starts, horizon)``. Against `dream` it tells the
    world's dynamics (the real actions do not take its car off the road) from its loop (they do,
    but its own driver does not act as the real one did)."""
    n, k, horizon, _ = actions.shape
    z, h_world = tiled(starts["z"], n), tiled(starts["h_world"], n)
    rows = actions.reshape(n * k, horizon, 2).astype(np.float32)
    off = np.zeros((n * k, horizon))
    for step in range(horizon):
        previous = rows[:, step - 1, 1] if step else np.tile(starts["previous"], n)
        z, h_world = world.transition(z, h_world, world_steering(np.ascontiguousarray(rows[:, step]), previous, shaping))
        if world.sampling[0] > 0:
            z = world.sample(h_world, step, z)
        off[:, step] = world.reward(z, h_world)[:, 1]
    return off.reshape(n, k, horizon)


def midmean(draws: np.ndarray) -> np.ndarray:
    """The interquartile mean over the first axis: the mean of the middle half of the draws, a
    quarter of them (rounded down) left off each end; with fewer than 4, their mean.

    >>> float(midmean(np.array([0.0, 0.1, 0.2, 0.3, 0.7, 0.8, 0.9, 1.0])))
    0.5
    >>> float(midmean(np.array([0.0, 0.0, 0.0, 1.0])))
    0.0
    """
    cut = len(draws) // 4
    return np.sort(draws, 0)[cut:len(draws) - cut].mean(0)


#: How a start's off-road share is read from its futures (``--off-road-read``): their mean, or the
#: mean of their middle half. Near the cliff where a steady pull lets go, a start's futures split
#: into cars that stay on and cars that leave, and their mean flattens the cliff: the dream is
#: over for pulls just short of it and under for those past it (docs/history/midmean.md).
OFF_ROAD_READS = {"mean": lambda draws: draws.mean(0), "midmean": midmean}


def dream_futures(driver: Simulator, world: Simulator, family: list, starts: dict, args, seed: int) -> dict:
    """`dream` ``args.futures`` times from the same starts, the world sampling with seeds 0, 1, ... (the
    first future is the one a run with one draws): the means of its figures over the futures
    (``off_road`` and ``off_steps`` read by ``args.off_road_read``, `OFF_ROAD_READS`), the first
    future's ``steer``, and ``spread`` ``(3, drivers)``, the standard deviation over the futures of
    a start's return, its rewards (without the value) and its off-road chance, averaged over the
    starts, and ``leaving``, each future's `rank_figures.leaving_counts` summed."""
    drawn = []
    for future in range(args.futures):
        if args.temperature > 0:
            world.set_sampling(args.temperature, future)
        drawn.append(dream(driver, world, family, starts, args.horizon, seed, args.value, args.world_steering,
                           args.through_frames))
    if args.temperature > 0:
        world.set_sampling(args.temperature, 0)  # the open loop draws as a run with one future
    out = {key: np.mean([d[key] for d in drawn], 0) for key in ("return", "rewards")}
    for key in ("off_road", "off_steps"):  # each decision's chance too, so the table agrees with the share
        out[key] = OFF_ROAD_READS[args.off_road_read](np.array([d[key] for d in drawn]))
    out["steer"] = drawn[0]["steer"]
    out["leaving"] = sum(leaving_counts(d["off_steps"]) for d in drawn)
    out["spread"] = np.stack([np.std([d[key] for d in drawn], 0).mean(1) for key in ("return", "rewards", "off_road")])
    return out

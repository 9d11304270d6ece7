"""Does the dream rank drivers as the real track does? A family of drivers, each the cloned
policy with one thing changed (steering gain, a steering bias, the target speed scaled, seeded
steering noise, a delay, and combinations), scored in gymnasium's real CarRacing and in the
dream from the same starts.

  python -m drivesim.carracing.rank --seeds 7000-7019 --out runs/rank --workers 2

Real: each driver drives each track (the env's reward over its 1000 frames, and the share of
decisions with no wheel on the road). Dream: from ``--starts`` states of the unchanged driver's
real drive of each track (its code, hidden state and speed at evenly spaced decisions), every
driver is rolled ``--horizon`` decisions in the dream, all of them stepped together in one batch:
the policy acts on the dream's codes, its action is changed as the driver changes it, the
transition steps with the speed the car would reach (``control.speed_after``), and the reward
head's rewards are summed (its off-road chance averaged). ``--value`` adds the value head at the
horizon. The report: each driver's real score and off-road share beside its dream return and
off-road chance; the Spearman rank correlation between the two over the family (and per track,
averaged), regret@1 (the real score lost by picking the dream's favourite, as a share of the
range between the best and the worst driver) and the Pearson correlation of the means; and the
dream's road memory: how well the unchanged driver's steering in the dream follows its real
steering from the same starts, decision by decision (the policy steers by the road it sees, so
the correlation falls where the dream's road stops being the real one), and how it steers on the
roads the dream makes up past that (its mean |steering| and change a decision from decision 11 on,
dream and real: the two agree where the made-up roads are as curvy and steady as the real ones).

``--futures N`` (with ``--temperature``) draws N futures from each start: the dream's figures are
their means, and each driver's spread over them is reported beside them, with its correlation over
the family with the dream's error in ranks (does the dream doubt where it is wrong?).
``--world-steering GAIN,LEAD`` steps the world with each steering s as ``GAIN * s + LEAD * (s - the
decision before's s)``, the drivers' memory with s: a diagnostic of the world's steering answer.

``--through-frames``: the drivers read the dream's frames through their encoder (150x slower).
``--world FILE`` dreams with another model's transition and heads (the drivers keep the policy of
``--weights`` and step its transition for their own memory): a world model is judged without
changing the drivers. ``--judge`` draws the world's futures through the built-in judge's sampler
(`Model.judge`, learnt for the default's world) with its settings, `JUDGE_STEERING`,
`JUDGE_TEMPERATURE` and `JUDGE_FUTURES`, unless ``--world-steering``, ``--temperature`` or
``--futures`` say otherwise (docs/judging.md).
``--out`` keeps every real drive (``real/DRIVER_SEED.json``, another ``--family``'s with its name
first; the behaviour drive in ``drive_SEED.npz``): a run that stops resumes where it was, and another
``--world`` or ``--horizon`` reuses the real drives; the report goes to ``rank.json`` (``--report``:
another name). The real drives are the drivers' of ``--weights``: ``drivers.json`` keeps what those
drivers answer to fixed inputs, and another ``--weights`` (or another built-in default) with the same
``--out`` is an error, not a report that mixes two families' drives (a folder from before this check
is taken as the next run's).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import sys
import time

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame draws off-screen
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np

from .._drivesim import Model, Simulator
from .._files import atomic_write
from .agents import ClonedAgent
from .control import speed_after
from .family import CHECK, CLIFF, FAMILIES, FAMILY, HOLDS, SMALL, ChangedAgent, Changes, Driver
from . import rank_real
from .rank_figures import (bend_sums, leaving, leaving_counts, made_up_roads, print_report, road_memory,
                           summary)
from .view import parse_seeds


# The judge's settings, chosen on the tuning tracks 15600-15619 (docs/history/judge_wheel.md): its
# world steps with each steering GAIN x (the default's transition answers the wheel short of the
# real car: probe-real 0.82-1.06x in 5 steps), at a temperature below 1 (hotter futures take a car
# with a steady pull off the road sooner than the real one leaves), and its figures are the means of
# 16 futures (with 4 a driver's dreamt off-road share still moves by 0.05 from one draw to another).
JUDGE_STEERING, JUDGE_TEMPERATURE, JUDGE_FUTURES = (1.4, 0.0), 0.7, 16


def dream_settings(args, own: dict) -> None:
    """Sets each of the dream's settings ``own`` names (``world_steering``, ``temperature``,
    ``futures``) that the command line left unset: the judge's with ``--judge``, else ``own``'s."""
    judge = {"world_steering": JUDGE_STEERING, "temperature": JUDGE_TEMPERATURE, "futures": JUDGE_FUTURES}
    for name, value in own.items():
        if getattr(args, name, None) is None:
            setattr(args, name, judge[name] if args.judge else value)


def start_decisions(decisions: int, starts: int, horizon: int, warmup: int) -> list:
    """Evenly spaced decisions of a drive ``decisions`` long, after the warm-up, each at least
    ``horizon`` before the end (a lap finished early ends the drive early)."""
    first, last = warmup + 8, decisions - horizon
    if last < first:
        raise ValueError(f"{decisions} decisions leave no start {horizon} decisions before the end")
    return sorted({int(round(x)) for x in np.linspace(first, last, starts)})


_model = None  # this process's model, loaded at its first job


def process_model(weights):
    """This process's model of ``weights`` (loaded once: the jobs of a run share one file)."""
    global _model
    if _model is None:
        _model = Model.load(weights)
    return _model


def dream_row_seed(seed: int, index: int, start: int, starts: int) -> int:
    """The steering noise's seed of driver ``index`` from start ``start`` of track ``seed``: the
    dream's row and the real window share it."""
    return seed * 1000 + index * starts + start


def kept_actions(drive: str) -> bool:
    """Whether the behaviour drive ``drive`` (``drive_SEED.npz``) kept its actions."""
    with np.load(drive) as f:
        return "actions" in f.files


def drive_name(args, index: int, seed: int) -> str:
    """The file of driver ``index``'s drive of track ``seed`` in ``--out``: the family's name
    first (families share ``--out`` and the behaviour drive), but for the full family, whose
    runs kept these names before there were others."""
    return f"{'' if args.family_name == 'all' else args.family_name + '_'}{index}_{seed}.json"


def real_job(job) -> dict:
    """One driver on one track: read from ``--out`` when an earlier run drove it (the behaviour
    drive again where ``--windows`` needs the actions an older run did not keep)."""
    args, index, seed = job
    path = os.path.join(args.out, "real", drive_name(args, index, seed))
    drive = os.path.join(args.out, f"drive_{seed}.npz")
    if os.path.exists(path) and not (index == 0 and args.windows and not kept_actions(drive)):
        with open(path) as f:
            return json.load(f)
    agent = ChangedAgent(args.family[index], seed=seed * 1000 + index, model=process_model(args.weights))
    figures, states, trace = rank_real.drive_real(agent, seed, args.frames, keep_states=index == 0)
    figures.update(driver=index, seed=seed)
    if index == 0:  # the behaviour drive: the dream's starts are states of it
        z, h, v, steer = (np.stack([s[i] for s in states]).astype(np.float32) for i in range(4))
        with atomic_write(drive) as f:
            np.savez(f, z=z, h=h, speed=v, steer=steer, first=np.int64(agent.warmup), **trace)
    with atomic_write(path) as f:
        f.write(json.dumps(figures).encode())
    return figures


def world_steering(action: np.ndarray, previous, shaping: tuple) -> np.ndarray:
    """The inputs ``(N, 2)`` the world steps with (``--world-steering GAIN,LEAD``, a diagnostic of
    its steering's answer): each steering ``GAIN * s + LEAD * (s - previous)``, ``previous`` the
    steering of the decision before; ``(1, 0)`` leaves them as they are."""
    gain, lead = shaping
    if (gain, lead) == (1.0, 0.0):
        return action
    shaped = action.copy()
    shaped[:, 1] = gain * action[:, 1] + lead * (action[:, 1] - previous)
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


def dream_futures(driver: Simulator, world: Simulator, family: list, starts: dict, args, seed: int) -> dict:
    """`dream` ``args.futures`` times from the same starts, the world sampling with seeds 0, 1, ...
    (the first future is the one a run with one draws): the means of its figures over the futures,
    the first future's ``steer``, and ``spread`` ``(3, drivers)``, the standard deviation over the
    futures of a start's return, its rewards (without the value) and its off-road chance,
    averaged over the starts."""
    drawn = []
    for future in range(args.futures):
        if args.temperature > 0:
            world.set_sampling(args.temperature, future)
        drawn.append(dream(driver, world, family, starts, args.horizon, seed, args.value, args.world_steering,
                           args.through_frames))
    if args.temperature > 0:
        world.set_sampling(args.temperature, 0)  # the open loop draws as a run with one future
    out = {key: np.mean([d[key] for d in drawn], 0) for key in ("return", "rewards", "off_road", "off_steps")}
    out["steer"] = drawn[0]["steer"]
    out["leaving"] = sum(leaving_counts(d["off_steps"]) for d in drawn)
    out["spread"] = np.stack([np.std([d[key] for d in drawn], 0).mean(1) for key in ("return", "rewards", "off_road")])
    return out


def report(args, results: list, windowed: list) -> dict:
    """The dream's side for every track (from the starts the real drives left), then the figures:
    against the whole real drives, and (``windowed``, ``rank_real.window_job``'s) against the real
    windows from the same starts (``windows``: the dream's rewards without the value; each
    decision's off-road share real, dreamt, and dreamt open loop on the real windows' inputs; and
    ``leaving``, whether the car comes back once off the road, `rank_figures.leaving`).
    With several ``--futures``, the dream's figures are their means, and each driver's spread
    over them is reported."""
    family, seeds = args.family, args.seeds
    batch = len(family) * args.starts
    driver = Simulator(Model.load(args.weights), batch=batch, threads=args.threads)
    world_model = (Model.judge if args.judge else Model.load)(args.world or args.weights)
    world = Simulator(world_model, batch=batch, threads=args.threads)
    real = {(r["driver"], r["seed"]): r for r in results}
    shape = (len(family), len(seeds))
    real_score, real_off, dream_return, dream_off, dream_rewards = (np.zeros(shape) for _ in range(5))
    spread = np.zeros((3, *shape))
    steer_dreamt, steer_real, dream_steps, open_steps = [], [], [], []
    dream_leaving = 0.0  # `leaving_counts` summed over the tracks
    got = {(w["driver"], w["seed"]): w for w in windowed}
    start = time.perf_counter()
    for t, seed in enumerate(seeds):
        with np.load(os.path.join(args.out, f"drive_{seed}.npz")) as f:
            starts = starts_of({k: f[k] for k in f.files}, world, world_model.hidden_dim, args.starts, args.horizon,
                               args.world_steering)
        d = dream_futures(driver, world, family, starts, args, seed)
        spread[:, :, t] = d["spread"]
        dream_return[:, t], dream_off[:, t] = d["return"].mean(1), d["off_road"].mean(1)
        dream_rewards[:, t] = d["rewards"].mean(1)
        dream_steps.append(d["off_steps"])
        dream_leaving += d["leaving"]
        if windowed:
            inputs = [rank_real.padded_to_horizon(got[i, seed]["actions"], args.horizon) for i in range(len(family))]
            open_steps.append(open_loop(world, starts, np.array(inputs), args.world_steering))
        steer_dreamt.append(d["steer"][0])
        steer_real.append(starts["steer"])
        for i in range(len(family)):
            real_score[i, t], real_off[i, t] = real[i, seed]["reward"], real[i, seed]["off_road"]
    seconds = time.perf_counter() - start
    several = args.futures > 1
    out = summary(family, real_score, real_off, dream_return, dream_off, spread[[0, 2]] if several else None)
    if windowed:
        win_return, win_off = np.zeros(shape), np.zeros(shape)
        for t, seed in enumerate(seeds):
            for i in range(len(family)):
                win_return[i, t], win_off[i, t] = np.mean(got[i, seed]["return"]), np.mean(got[i, seed]["off_road"])
        out["windows"] = summary(family, win_return, win_off, dream_rewards, dream_off,
                                 spread[[1, 2]] if several else None)
        out["windows"]["per_track"] = {"real": win_return.tolist(), "dream": dream_rewards.tolist()}
        real_steps = [[rank_real.padded_to_horizon(got[i, seed]["off"], args.horizon) for seed in seeds]
                      for i in range(len(family))]
        flags, road = np.reshape(real_steps, (len(family), -1, args.horizon)), np.concatenate(steer_real)
        out["windows"]["leaving"] = leaving(family, leaving_counts(flags), dream_leaving, bend_sums(flags, road),
                                            road.mean())
        out["windows"]["off_by_decision"] = {"real": np.mean(real_steps, (1, 2)).tolist(),
                                             "dream": np.concatenate(dream_steps, 1).mean(1).tolist(),
                                             "open_loop": np.concatenate(open_steps, 1).mean(1).tolist()}
    if family[0] == Driver(family[0].name):  # unchanged: its real drive is the behaviour drive
        steer_dreamt, steer_real = np.concatenate(steer_dreamt), np.concatenate(steer_real)
        out["road_memory"] = road_memory(steer_dreamt, steer_real)
        out["made_up_roads"] = made_up_roads(steer_dreamt, steer_real)
    out.update(seeds=seeds, horizon=args.horizon, starts=args.starts, temperature=args.temperature,
               futures=args.futures, world_steering=list(args.world_steering), value=args.value,
               through_frames=args.through_frames, frames=args.frames, weights=args.weights, world=args.world, judge=args.judge,
               dream_decisions_per_second=len(family) * args.starts * args.horizon * len(seeds) * args.futures / seconds,
               per_track={"real": real_score.tolist(), "dream": dream_return.tolist()})
    return out


def load_model(parser: argparse.ArgumentParser, flag: str, path: str | None, judge: bool = False) -> Model:
    """The model of ``path`` (None: the built-in default; `Model.judge`'s), or the parser's error naming ``flag``."""
    try:
        return (Model.judge if judge else Model.load)(path)
    except (OSError, ValueError) as e:
        parser.error(f"{flag}: {e}")


def shaping(text: str) -> tuple:
    """``--world-steering``'s GAIN[,LEAD] (LEAD 0 where not given), both finite."""
    parts = [float(x) for x in text.split(",")]
    if len(parts) not in (1, 2) or not np.isfinite(parts).all():
        raise ValueError(text)
    return (parts[0], parts[1] if len(parts) == 2 else 0.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing.rank", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=parse_seeds, required=True, help="track seeds, e.g. 7000-7019")
    p.add_argument("--out", required=True, help="folder for the real drives and the report (resumable)")
    p.add_argument("--weights", help="the drivers' weight file: their policy (default: the built-in model)")
    p.add_argument("--world", help="the world model's weight file: the transition and heads that dream (default: --weights)")
    p.add_argument("--judge", action="store_true", help="the world's futures drawn by the built-in judge (Model.judge)")
    p.add_argument("--world-steering", type=shaping, metavar="GAIN[,LEAD]",
                   help="the world steps with GAIN * s + LEAD * (s - the decision before's s) for each steering s "
                        "(the drivers' memory steps with s); default 1, with --judge JUDGE_STEERING")
    p.add_argument("--family", choices=list(FAMILIES), default="all",
                   help=f"all: the {len(FAMILY)} drivers; small: {len(SMALL)} (tests); holds: the clone and "
                        f"{len(HOLDS) - 1} constant steerings, hands off among them (with --windows --horizon 20); "
                        f"check: {len(CHECK)} other drivers, none of them another family's "
                        "(a second family, for a world tuned on all); cliff: the clone and "
                        f"{len(CLIFF) - 1} steady pulls either side of where it lets go")
    p.add_argument("--horizon", type=int, default=40, help="dream decisions from each start")
    p.add_argument("--starts", type=int, default=7, help="starts per track")
    p.add_argument("--temperature", type=float,
                   help="sampled futures (0: the mean dream, the default; with --judge JUDGE_TEMPERATURE)")
    p.add_argument("--futures", type=int,
                   help="sampled futures from each start (with --temperature): the dream's figures their means, "
                        "and each driver's spread over them reported (default 1; with --judge JUDGE_FUTURES)")
    p.add_argument("--value", action="store_true", help="add the value head at the horizon")
    p.add_argument("--through-frames", action="store_true",
                   help="the drivers read the dream's frames through their encoder (as a real drive), not its codes")
    p.add_argument("--frames", type=int, default=1000, help="env frames per real drive (CarRacing-v3: 1000)")
    p.add_argument("--workers", type=int, default=1, help="real drives at once, each in its own process")
    p.add_argument("--threads", type=int, default=1, help="threads of the dream's simulator")
    p.add_argument("--windows", action="store_true",
                   help="also drive every driver in the real env from the dream's starts, --horizon decisions")
    p.add_argument("--report", default="rank.json", help="the report's file name in --out")
    args = p.parse_args(argv)
    dream_settings(args, {"world_steering": (1.0, 0.0), "temperature": 0.0, "futures": 1})
    if min(args.horizon, args.starts, args.frames, args.workers, args.threads, args.futures) < 1 \
            or not args.temperature >= 0:
        p.error("--horizon, --starts, --frames, --workers, --threads and --futures must be positive, --temperature >= 0")
    if args.judge and args.temperature == 0:
        p.error("--judge needs --temperature above 0: the mean dream draws no futures")
    if args.futures > 1 and args.temperature == 0:
        p.error("--futures above 1 needs --temperature above 0: the mean dream has one future")
    try:
        start_decisions(args.frames // ClonedAgent.frame_skip, args.starts, args.horizon, ClonedAgent.warmup)
    except ValueError as e:
        p.error(str(e))
    # Before any drive: a bad file is an error now, not after the real drives.
    drivers = load_model(p, "--weights", args.weights)
    if drivers.policy_width is None:
        p.error("--weights: the model has no policy to drive with")
    if args.world or args.judge:
        load_model(p, "--world" if args.world else "--judge", args.world or args.weights, args.judge)
    args.family_name, args.family = args.family, FAMILIES[args.family]
    os.makedirs(os.path.join(args.out, "real"), exist_ok=True)
    try:
        rank_real.check_drivers(args.out, rank_real.drivers_fingerprint(drivers))
    except ValueError as e:
        p.error(str(e))
    # Each track's unchanged driver first: its drive leaves the dream's starts.
    jobs = [(args, i, seed) for i in range(len(args.family)) for seed in args.seeds]
    results, windowed, started = [], [], time.perf_counter()
    with multiprocessing.Pool(min(args.workers, len(jobs))) if args.workers > 1 else contextlib.nullcontext() as pool:
        for r in (pool.imap_unordered(real_job, jobs) if pool else map(real_job, jobs)):
            results.append(r)
            print(f"[{len(results)}/{len(jobs)}, {time.perf_counter() - started:.0f} s] {args.family[r['driver']].name} "
                  f"on track {r['seed']}: {r['reward']:.1f}, off the road {r['off_road']:.1%}", flush=True)
        if args.windows:  # the behaviour drives are all kept now
            os.makedirs(rank_real.windows_dir(args), exist_ok=True)
            for w in (pool.imap_unordered(rank_real.window_job, jobs) if pool else map(rank_real.window_job, jobs)):
                windowed.append(w)
                print(f"[windows {len(windowed)}/{len(jobs)}, {time.perf_counter() - started:.0f} s] "
                      f"{args.family[w['driver']].name} on track {w['seed']}: {np.mean(w['return']):.1f} a window, "
                      f"off the road {np.mean(w['off_road']):.1%}", flush=True)
    out = report(args, results, windowed)
    with atomic_write(os.path.join(args.out, args.report)) as f:
        f.write(json.dumps(out, indent=1).encode())
    print_report(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

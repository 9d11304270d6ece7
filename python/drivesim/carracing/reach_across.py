"""How far across the road the dream carries the car under a recording's own actions: from windows
of recorded drives (failure drives show the car leaving the road), the world dreams on from 5 real
frames with the recorded speed and steering, no driver in the loop, and at a few fed-back steps
the place across the road is read off the dreamt frame and off the real one (`rank_sight.across`).

  python -m drivesim reach-across --episodes failures.safetensors.gz [--judge] [--report reach.json]

The real car that leaves the road travels on across the grass, the road still beside it, and
loses it from its rows mostly once it is 2 or more half-roads out; a world whose dreamt car stays
near the edge and whose road fades there instead drives its failing drivers off the road by
losing it (docs/history/lateral_reach.md). For each fed-back step of `STEPS` the report gives,
real and dreamt, the shares of windows with the road gone from beside the car (``gone``), with the
car `EDGE` to `FAR` half-roads out (``edge``) and `FAR` or more out (``far``). No driver is in
the loop and no env is needed: half a minute on a recording, where `rank-sight` drives the real
windows again. And (``clone``) what the clone (``--weights``) would steer at each of those steps,
on the real frames' codes and on the dream's, against the place it was seen at: a line whose
slope is the clone's gain, the steering a half-road off the centre brings. Where the dream's is
short of the real one, the clone takes back less in the dream at the same place: a pull rides
further out, a weave does not grow.

``--world`` the world's weight file (default: the built-in model), ``--judge`` its futures drawn
by the judge's sampler with the judge's steering and temperature (`rank.JUDGE_STEERING`,
`rank.JUDGE_TEMPERATURE`), else ``--temperature`` (0: the mean dream) and ``--world-steering``.
Window ``i`` samples with seed ``--seed + i``: the same file and flags, the same figures.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from .. import episodes
from .._batches import batched
from .._drivesim import Simulator
from .._files import atomic_write
from . import rank, rank_dream
from .rank_sight import across

# Real frames seed each dream, as the transition's training windows (sequences.TEACHER).
SEEDS = 5
# The fed-back steps read (the last one is a window's length past its seeds).
STEPS = (5, 10, 20, 35)
# Half-roads from the road's centre: at the edge (the wheels leave the road from about 1.25), and
# far out (the real road is still beside a car 1.5-2 out in 99 % of frames).
EDGE, FAR = 1.0, 1.5


def window_starts(bounds: list, every: int) -> np.ndarray:
    """The first frame of each window: every ``every`` frames of each episode, where its seeds and
    the last step of `STEPS` fit."""
    length = SEEDS + STEPS[-1]
    return np.array([t for s, e in bounds for t in range(s, e - length + 1, every)], np.int64)


def bands(places: np.ndarray) -> dict:
    """The shares of ``places`` (half-roads, NaN: the road gone) gone, at the edge and far out."""
    out = np.abs(np.nan_to_num(places, nan=0.0))
    gone = np.isnan(places)
    return {"gone": float(gone.mean()), "edge": float(((out >= EDGE) & (out < FAR) & ~gone).mean()),
            "far": float(((out >= FAR) & ~gone).mean())}


def reach(world: Simulator, data: episodes.Episodes, every: int = 10, temperature: float = 0.0,
          shaping: tuple = (1.0, 0.0), seed: int = 0, driver: Simulator | None = None, memory_dim: int = 0) -> dict:
    """The real and the dreamt places at each step of `STEPS`, ``{"windows", "real", "dream"}``,
    each side ``{step: bands}`` (module docstring). The dream's inputs are the recorded ones, its
    steering shaped as ``rank`` shapes a dream's (`rank_dream.world_steering`) from the first
    predicted step on; the seeds' actions stay as recorded, as the real frames were driven. With
    ``driver`` (the clone's simulator, its hidden state ``memory_dim`` wide) also ``"clone"``:
    its steering against the place on the real frames' codes and on the dream's (`clone_gain`)."""
    starts = window_starts(data.bounds(), every)
    if not len(starts):
        raise ValueError(f"no episode holds a window of {SEEDS + STEPS[-1]} frames: record longer drives")
    frame_of_step = SEEDS - 1 + np.array(STEPS)  # fed-back step k shows the window's frame SEEDS - 1 + k
    codes = []
    for i, s in enumerate(starts):
        recorded = data.actions[s:s + SEEDS - 1 + STEPS[-1]]
        actions = recorded.copy()
        actions[SEEDS - 1:] = rank_dream.world_steering(recorded[SEEDS - 1:], recorded[SEEDS - 2:-1, 1], shaping)
        world.set_sampling(temperature, seed + i)
        seeds = np.ascontiguousarray(data.frames[s:s + SEEDS])
        codes.append(np.concatenate([world.encode(seeds), world.rollout(seeds, np.ascontiguousarray(actions))]))
    codes = np.stack(codes)  # (windows, frames, z): the seeds' codes, then the dreamt ones
    dreamt = across(batched(world.generate, codes[:, frame_of_step].reshape(-1, codes.shape[2]), world.batch))
    dreamt = dreamt.reshape(len(starts), len(STEPS))
    frames = starts[:, None] + np.arange(codes.shape[1])
    real = across(data.frames[frames[:, frame_of_step].ravel()]).reshape(len(starts), len(STEPS))
    report = {"windows": len(starts),
              "real": {str(k): bands(real[:, j]) for j, k in enumerate(STEPS)},
              "dream": {str(k): bands(dreamt[:, j]) for j, k in enumerate(STEPS)}}
    if driver is not None:
        seen = batched(driver.encode, data.frames, driver.batch)[frames]
        window_actions = data.actions[frames[:, :-1]]
        report["clone"] = {
            "real": clone_gain(clone_steering(driver, seen, window_actions, memory_dim)[:, frame_of_step], real),
            "dream": clone_gain(clone_steering(driver, codes, window_actions, memory_dim)[:, frame_of_step], dreamt)}
    return report


def clone_steering(driver: Simulator, codes: np.ndarray, actions: np.ndarray, memory_dim: int) -> np.ndarray:
    """The clone's steering ``(windows, frames)`` on each code of ``codes`` ``(windows, frames, z)``,
    its memory stepped on them with ``actions`` ``(windows, frames - 1, 2)`` from an empty one, as
    a drive steps it (it acts on what it sees, then its memory takes it in: `rank_dream.dream`)."""
    out = np.empty(codes.shape[:2], np.float32)
    for a in range(0, len(codes), driver.batch):
        z = codes[a:a + driver.batch]
        h = np.zeros((len(z), memory_dim), np.float32)
        for t in range(z.shape[1]):
            seen = np.ascontiguousarray(z[:, t])
            out[a:a + len(z), t] = driver.act(seen, h)[:, 1]
            if t < actions.shape[1]:
                h = driver.transition(seen, h, np.ascontiguousarray(actions[a:a + len(z), t], np.float32))[1]
    return out


def clone_gain(steering: np.ndarray, places: np.ndarray) -> dict:
    """A line through the clone's ``steering`` against the ``places`` it was seen at, where the
    road is beside a car within `FAR` half-roads of its centre: ``{"gain", "offset", "points"}``
    (the gain in steering a half-road; None with fewer than two places)."""
    steering, places = np.ravel(steering), np.ravel(places)
    ok = ~np.isnan(places) & (np.abs(np.nan_to_num(places)) < FAR)
    if len(np.unique(places[ok])) < 2:
        return {"gain": None, "offset": None, "points": int(ok.sum())}
    gain, offset = np.polyfit(places[ok], steering[ok], 1)
    return {"gain": float(gain), "offset": float(offset), "points": int(ok.sum())}


def print_report(report: dict, out=sys.stdout) -> None:
    print(f"{report['windows']} windows; road gone / 1.0-1.5 half-roads out / 1.5 or more out, real; dream:", file=out)
    for k in STEPS:
        r, d = report["real"][str(k)], report["dream"][str(k)]
        print(f"  step {k:2d}: {r['gone']:.2f} / {r['edge']:.2f} / {r['far']:.2f};  "
              f"{d['gone']:.2f} / {d['edge']:.2f} / {d['far']:.2f}", file=out)
    if "clone" in report:
        line = ["-" if c["gain"] is None else f"{c['offset']:+.3f} {c['gain']:+.3f} x place ({c['points']})"
                for c in (report["clone"]["real"], report["clone"]["dream"])]
        print(f"the clone's steering against the place (the road beside the car, within {FAR} half-roads): "
              f"real {line[0]}; dream {line[1]}", file=out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing.reach_across", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", required=True, help="recorded drives (`record`, `failures`): frames and actions")
    p.add_argument("--weights", help="the clone's weight file, as `rank`'s drivers (default: the built-in model)")
    p.add_argument("--world", help="the world model's weight file (default: the built-in model)")
    p.add_argument("--judge", action="store_true", help="the world's futures drawn by the built-in judge (Model.judge)")
    p.add_argument("--temperature", type=float, help="the dream's (0: the mean dream, the default; with --judge "
                                                     "rank.JUDGE_TEMPERATURE)")
    p.add_argument("--world-steering", type=rank.shaping, metavar="GAIN[,LEAD]",
                   help="the world steps with GAIN x each steering and LEAD x its change, held at full lock "
                        "(default 1, with --judge rank.JUDGE_STEERING)")
    p.add_argument("--every", type=int, default=10, help="frames between windows' starts")
    p.add_argument("--seed", type=int, default=0, help="window i samples with seed SEED + i")
    p.add_argument("--report", help="a JSON file for the figures")
    args = p.parse_args(argv)
    rank.dream_settings(args, {"world_steering": (1.0, 0.0), "temperature": 0.0})
    if args.every < 1 or not 0 <= args.temperature <= 100 or not 0 <= args.seed < 2 ** 63:
        p.error("--every must be at least 1, --temperature from 0 to 100, --seed from 0 to 2^63 - 1")
    if args.judge and args.temperature == 0:
        p.error("--judge needs --temperature above 0: the mean dream draws no futures")
    model = rank.load_model(p, "--world" if args.world else "--judge", args.world, args.judge)
    clone = rank.load_model(p, "--weights", args.weights)
    try:
        data = episodes.read(args.episodes)
        report = reach(Simulator(model, batch=64), data, args.every, args.temperature, args.world_steering, args.seed,
                       Simulator(clone, batch=64), clone.hidden_dim)
        report.update(episodes=args.episodes, weights=args.weights, world=args.world, judge=args.judge,
                      temperature=args.temperature, world_steering=list(args.world_steering), every=args.every,
                      seed=args.seed)
        print_report(report)
        if args.report:
            with atomic_write(args.report) as f:
                f.write(json.dumps(report, indent=1).encode())
    except (OSError, ValueError) as e:
        print(f"reach_across: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Paired steering branches: the steering probe's experiment (`probe_real`) recorded as training
data, so that a world model can learn what the steering does on its own.

In every recording the steering follows the road: the driver steers because the road bends, so a
transition trained on it can put down to the steering what the road was doing anyway (the probe
finds the dream's road moving the wrong way a step after the wheel turns, and half as far as the
real one after five; docs/judging.md). Here the same state is driven three ways: a scripted
driver (`record`'s styles) drives each track; every ``--every`` decisions a point, and from each
point three branches of ``--horizon`` decisions steering a constant -x, 0 and +x (x drawn from
``--steer``, 0.15 to 0.7 unless told), gas and brake holding the point's speed as the probe does.
With ``--offsets`` the driver drives on in each branch, its own steering moved by -x, 0 and +x
(clipped to full lock): pulled hands that the driver keeps correcting, what a steering bias does.
With ``--noise`` it drives on with its steering moved by -x n_t, 0 and +x n_t, n_t one draw of
standard normal noise a decision, the same draws in a point's three branches: unsteady hands, a
kick every decision, what the rank probe's noisy drivers do (the real car leaves the road under
them within a second, the dream later; docs/judging.md).
The track is replayed from its seed to the point for each branch, the driver acting again
(CarRacing is deterministic: the replayed frame is the recorded one, which the run checks).
``--driver clone`` drives with the default's cloned policy at its own speed instead, the rank probe's
drivers' base: its pulled and unsteady hands are the family's. Each branch is an episode: the drive's 5 frames up to the
point (its recorded actions between them), then the branch's frames, with the env's reward, the
tiles and ``on_road``; the three branches of a point are consecutive, -x first.

  python -m drivesim branches --seeds 14000-14019 --driver hard --workers 2 --out branches.safetensors.gz
  python -m drivesim branches --seeds 14300-14319 --offsets --steer 0.05,0.4 --out offsets.safetensors.gz
  python -m drivesim branches --seeds 15300-15319 --driver clone --noise --steer 0.1,0.8 --out noise.safetensors.gz
"""

import argparse
import os
import sys
from multiprocessing import Pool

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame renders off-screen
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np

from .. import episodes, probe
from . import record, view
from .probe_real import held, steps
from .record import car_racing

SKIP = 4  # the recordings' frame skip (12.5 decisions a second)
STEER = (0.15, 0.7)  # the range x is drawn from unless --steer says otherwise


def started(seed, draw_last):
    """CarRacing on track ``seed`` past its zoom (its last step drawn where ``draw_last``)."""
    env = car_racing.CarRacing()
    env.reset(seed=seed)
    steps(env, np.array([0.0, 0.3, 0.0], np.float32), record.WARMUP_STEPS, draw_last)
    return env


#: The driver that is the default's cloned policy, not a scripted one: the rank probe's drivers' own.
CLONE = "clone"
_model = None  # the default model, loaded once a process for the clone's branches


class CloneDriver:
    """The default's cloned policy at its own speed (no racing pace, no bearings: the rank probe's
    drivers' base) behind the scripted drivers' ``act(car, frame_seconds)``: it reads the env's
    view, so every decision's frame is drawn. It starts past its warm-up, where `started` leaves
    the env, with an empty memory; its memory (``agent.h``) is all its state, so a branch replays
    the drive's actions as recorded and gives it the memory it had at the point."""

    def __init__(self, env):
        global _model
        from .._drivesim import Model
        from .cloned import ClonedAgent

        if _model is None:
            _model = Model.load()
        self.env, self.agent = env, ClonedAgent(_model, pace=None, bearings=False)
        self.agent.decisions = self.agent.warmup

    def act(self, car, frame_seconds):
        action = self.agent.act(view.observe(self.env), view.speed(self.env))
        return action, view.speed(self.env), None


def driver_of(env, seed, style):
    """The driver of ``seed``'s drive, as `base_drive` starts it: scripted, or `CloneDriver`."""
    if style == CLONE:
        return CloneDriver(env)
    return record.Driver(env.track, np.random.default_rng(seed), style)


def base_drive(seed, style, frames):
    """The driver's drive of ``seed``: its frames, actions (speed, steering), the env's actions
    and, one a decision, `episodes.REWARDS`' reward, tiles and ``on_road`` (the clone's: also its
    memory before each decision)."""
    env = started(seed, True)
    driver = driver_of(env, seed, style)
    drive = {"frames": [], "actions": [], "applied": [], "reward": [], "tiles": [], "on_road": []}
    while len(drive["frames"]) < frames and not record.off_playfield(env.car):
        if style == CLONE:
            drive.setdefault("memory", []).append(driver.agent.h.copy())
        action, speed, _ = driver.act(env.car, SKIP / car_racing.FPS)
        drive["frames"].append(view.observe(env))
        drive["actions"].append((speed, action[0]))
        drive["applied"].append(np.asarray(action, np.float32))
        drive["on_road"].append(record.wheel_on_road(env.car))
        tiles = env.tile_visited_count
        drive["reward"].append(steps(env, action, SKIP, True))
        drive["tiles"].append(env.tile_visited_count - tiles)
    env.close()
    return drive


def branch(seed, style, drive, point, steer, horizon, kind="held", noise=None):
    """One branch (an `episodes.Episodes`) from decision ``point`` of ``drive`` (`base_drive`'s by
    ``style``) for ``horizon`` decisions, steering ``steer`` (``kind`` "held"), the driver's own
    steering plus ``steer`` ("offsets") or plus ``steer * noise[t]`` at the branch's decision t
    ("noise"; ``noise`` at least ``horizon + 1`` draws), and how far the replayed frame at the
    point is from the recorded one (mean absolute difference, 0-255)."""
    env = started(seed, point == 0)
    driver = driver_of(env, seed, style)
    for i in range(point):
        if style == CLONE:  # its memory is its state: given below, the drive's actions replayed
            action = drive["applied"][i]
        else:  # the driver acts again so that its own state (its noise, its aims) is the drive's at the point
            action, _, _ = driver.act(env.car, SKIP / car_racing.FPS)
            if not np.array_equal(action, drive["applied"][i]):
                raise RuntimeError(f"track {seed}: the driver's replay differs from its drive at decision {i}")
        steps(env, action, SKIP, i + 1 == point)
    if style == CLONE:
        driver.agent.h = drive["memory"][point].copy()
    replayed = float(np.abs(view.observe(env).astype(np.int16) - drive["frames"][point]).mean())
    first = point - probe.SEEDS + 1
    out = {k: list(drive[k][first:point]) for k in ("frames", "actions", "reward", "tiles", "on_road")}
    out["frames"].append(drive["frames"][point])
    speed = drive["actions"][point][0]

    def action_now(t):
        if kind == "held":
            return held(steer, speed, view.speed(env))
        action = driver.act(env.car, SKIP / car_racing.FPS)[0]
        action[0] = np.clip(action[0] + steer * (noise[t] if kind == "noise" else 1.0), -1.0, 1.0)
        return action

    for t in range(horizon):
        action = action_now(t)
        out["actions"].append((view.speed(env), float(action[0])))
        out["on_road"].append(record.wheel_on_road(env.car))
        tiles = env.tile_visited_count
        out["reward"].append(steps(env, action, SKIP, True))
        out["tiles"].append(env.tile_visited_count - tiles)
        out["frames"].append(view.observe(env))
    # The last frame's action is never stepped: its steering the branch's next, its reward none.
    out["actions"].append((view.speed(env), float(action_now(horizon)[0])))
    out["on_road"].append(record.wheel_on_road(env.car))
    out["reward"].append(0.0)
    out["tiles"].append(0)
    env.close()
    rewards = {k: np.array(out[k], dtype=episodes.REWARDS[k]) for k in episodes.REWARDS}
    return episodes.Episodes(np.stack(out["frames"]), np.array(out["actions"], np.float32), np.zeros(1, np.int64),
                             rewards), replayed


def track_branches(job):
    """Every point's three branches on one track (`main`'s job): a list of episodes."""
    seed, style, frames, every, horizon, steer_range, kind = job
    drive = base_drive(seed, style, frames)
    rng = np.random.default_rng(seed + 1_000_003)
    out, worst = [], 0.0
    for point in range(probe.SEEDS - 1 + every // 2, len(drive["frames"]), every):
        x = rng.uniform(*steer_range)
        noise = rng.standard_normal(horizon + 1) if kind == "noise" else None  # the three branches' draws
        for steer in (-x, 0.0, x):
            episode, replayed = branch(seed, style, drive, point, float(steer), horizon, kind, noise)
            out.append(episode)
            worst = max(worst, replayed)
    if worst > 1.0:
        raise RuntimeError(f"track {seed}: the replay drifted from the recording (mean difference {worst:.2f})")
    print(f"track {seed}: {len(out) // 3} points, {len(out)} branches", flush=True)
    return out


def steer_range(text):
    """``--steer``'s ``LO,HI`` (0 < LO <= HI <= 1)."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not LO,HI") from None
    if not 0.0 < lo <= hi <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: want 0 < LO <= HI <= 1")
    return lo, hi


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m drivesim branches", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=view.parse_seeds, required=True, help="track seeds, e.g. 14000-14019")
    p.add_argument("--driver", choices=record.DRIVERS + (CLONE,), default="hard",
                   help="the scripted driver of the drives, or the default's cloned policy (clone)")
    p.add_argument("--frames", type=int, default=300, help="decisions of each track's drive")
    p.add_argument("--every", type=int, default=25, help="decisions between branch points")
    p.add_argument("--horizon", type=int, default=20, help="decisions of each branch")
    p.add_argument("--steer", type=steer_range, default=STEER, metavar="LO,HI",
                   help="the range x is drawn from (0 < LO <= HI <= 1; default 0.15,0.7)")
    moved = p.add_mutually_exclusive_group()
    moved.add_argument("--offsets", action="store_true",
                       help="the driver drives on, its steering moved by -x, 0, +x (else a constant -x, 0, +x)")
    moved.add_argument("--noise", action="store_true",
                       help="the driver drives on, its steering moved by -x n_t, 0, +x n_t (n_t standard normal)")
    p.add_argument("--workers", type=int, default=os.cpu_count(), help="tracks at once, each in its own process")
    p.add_argument("--out", required=True, help="episodes file (.safetensors or .safetensors.gz)")
    args = p.parse_args(argv)
    if min(args.frames, args.every, args.horizon, args.workers) < 1:
        p.error("--frames, --every, --horizon and --workers must be positive")
    if args.frames < probe.SEEDS + args.every // 2:
        p.error(f"--frames {args.frames} leaves no branch point (the first is after {probe.SEEDS - 1 + args.every // 2})")
    kind = "offsets" if args.offsets else "noise" if args.noise else "held"
    jobs = [(s, args.driver, args.frames, args.every, args.horizon, args.steer, kind) for s in args.seeds]
    with Pool(min(args.workers, len(jobs))) as pool:
        parts = pool.map(track_branches, jobs, chunksize=1)
    data = episodes.Episodes.concat([e for part in parts for e in part])
    meta = {"source": "gymnasium CarRacing-v3 steering branches (python -m drivesim branches)",
            "seeds": ",".join(map(str, args.seeds)), "driver": args.driver, "branches": "3",
            "horizon": str(args.horizon), "frame_hz": str(car_racing.FPS / SKIP),
            "steer": f"{args.steer[0]},{args.steer[1]}", "kind": kind}
    episodes.write(args.out, data, meta)
    print(f"wrote {args.out}: {len(data) // 3} points, {len(data)} branches, {len(data.frames)} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())

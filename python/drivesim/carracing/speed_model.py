"""How the car's speed answers ``speed_control``: the data behind the planners' speed model.

A policy gives the speed to drive at; ``speed_control`` turns it into gas and brake, and the car
gets there at its own pace. The transition learnt from the speedometer's speed, so a dream must
be stepped with the speed the car would have, not with the target (``carracing.control
.speed_after``). This drives the cloned agent of ``--weights`` on ``--seeds`` and, for every
decision on the road, compares the speed a decision later with what the model says and with the
target itself (what the planners stepped their dreams with before):

  python -m drivesim speed-model --weights W --seeds 6000-6001 6005

It prints the change of speed against the gap to the target, by band, and both RMS errors.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import numpy as np

from . import record

BANDS = [(-60, -10), (-10, -4), (-4, 0), (0, 4), (4, 10), (10, 20), (20, 40), (40, 100)]


def drive(weights, seeds: list, frames: int = 1000) -> np.ndarray:
    """Rows (speed, target, speed a decision later) of the decisions on the road, ``frames`` env
    frames a track at most."""
    import gymnasium
    from .._drivesim import Model
    from .agents import ClonedAgent
    from .view import decision_steps, observe, speed

    agent, rows = ClonedAgent(Model.load(weights), pace=None), []
    for seed in seeds:
        env = gymnasium.make("CarRacing-v3", max_episode_steps=frames)
        env.reset(seed=seed)
        agent.reset()
        done, last = False, None
        while not done:
            view, now = observe(env), speed(env)
            if last is not None:
                rows.append((*last, now))
            action = agent.act(view, now)
            on_road = any(len(w.tiles) > 0 for w in env.unwrapped.car.wheels)
            last = None
            if agent.decisions > agent.warmup and on_road:
                z, h, _ = agent.last_state
                last = (now, float(agent.sim.act(z, h)[0]))
            for _, _, terminated, truncated, _ in decision_steps(env, action, agent.frame_skip):
                if terminated or truncated:
                    done = True
                    break
        env.close()
    return np.array(rows, np.float64).reshape(-1, 3)


def rms_errors(rows: np.ndarray) -> tuple[float, float]:
    """The RMS error of the speed a decision later: the model's, and the target's."""
    from .control import speed_after

    speed, target, later = rows.T
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))
    return rms(speed_after(speed, target) - later), rms(target - later)


def main(argv=None) -> int:
    from .control import speed_after

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", help="weight file with a policy (default: the built-in model)")
    p.add_argument("--seeds", nargs="+", required=True, help="tracks, e.g. 6000-6001 6005")
    p.add_argument("--frames", type=int, default=1000, help="env frames a track at most")
    args = p.parse_args(argv)
    seeds = [s for text in args.seeds for s in record.parse_seeds(text)]
    if args.frames < 1:
        p.error("--frames must be positive")
    rows = drive(args.weights, seeds, args.frames)
    if not len(rows):
        raise SystemExit("speed-model: no decision on the road to measure (more --frames or other --seeds)")
    speed, target, later = rows.T
    gap, change = target - speed, later - speed
    print(f"{len(speed)} decisions on the road; target - speed: mean {gap.mean():.1f}, sd {gap.std():.1f}")
    print("   gap band   decisions  change of speed (mean, sd)  the model's")
    for lo, hi in BANDS:
        m = (gap >= lo) & (gap < hi)
        if m.sum():
            model = speed_after(speed[m], target[m]) - speed[m]
            print(f"  {lo:4d}..{hi:4d}  {m.sum():9d}  {change[m].mean():+8.2f} {change[m].std():6.2f}  {model.mean():+12.2f}")
    model_rms, target_rms = rms_errors(rows)
    print(f"RMS error of the speed a decision later: the model {model_rms:.2f}, the target {target_rms:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

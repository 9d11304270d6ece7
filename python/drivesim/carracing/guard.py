"""How often `mpc`'s guard lets the candidates in, with a given world: the guard's figure (the
dream's off-road chance of the policy's own plan, over its futures) at every planned decision of
drives where the policy alone decides, and the share of decisions at or above each guard.

  python -m drivesim guard --seeds 6000-6031 --workers 2
  python -m drivesim guard --seeds 6000-6031 --weights old.safetensors --rate 0.01

`mpc` is driven with a guard no chance reaches (so every decision is the cloned driver's, at
racing pace, and the drives are the same whatever the world predicts); the figure is the one
`mpc` compares with its guard. A world that is more pessimistic about the policy's own plan trips
a guard more often, and each trip lets the candidates' small moves change the lap: a new world's
guard is set where its share of trips is what the old world's was at its guard
(``--rate``: the guard giving that share; docs/planning.md, "The guard set for the world").
"""

from __future__ import annotations

import argparse
import sys
from multiprocessing import Pool

import numpy as np

from .view import parse_seeds

#: The guards whose shares are printed unless told.
GUARDS = (0.02, 0.05, 0.07, 0.1, 0.15, 0.2)


def figures(job) -> list:
    """The guard's figure at each planned decision of one track's drive (`main`'s job)."""
    from .__main__ import drive
    from .agents import make_agent

    weights, seed, frames = job
    agent = make_agent("mpc", weights=weights)
    agent.guard = 2.0  # above any chance (the option stops at 1, which a sure chance reaches): the policy decides
    chances = []
    plan = agent.plan

    def recorded(z, h, speed):
        out = plan(z, h, speed)
        chances.append(agent.chance)
        return out

    agent.plan = recorded
    drive(agent, seed, frames)
    return chances


def guard_for(chances: np.ndarray, rate: float) -> float:
    """The guard that ``chances`` (the figures of many decisions) reach at share ``rate`` of them."""
    return float(np.quantile(chances, 1.0 - rate))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing.guard", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=parse_seeds, required=True, help="track seeds, e.g. 6000-6031")
    p.add_argument("--weights", help="the model's weight file (default: the built-in model)")
    p.add_argument("--guards", default=",".join(map(str, GUARDS)), help="guards to give the share of trips for")
    p.add_argument("--rate", type=float, help="also the guard tripped at this share of decisions (0 to 1)")
    p.add_argument("--frames", type=int, default=1000, help="env frames of each drive")
    p.add_argument("--workers", type=int, default=1, help="tracks at once, each in its own process")
    args = p.parse_args(argv)
    try:
        guards = [float(g) for g in args.guards.split(",")]
    except ValueError:
        p.error(f"--guards {args.guards!r}: expected numbers separated by commas")
    if not all(0.0 <= g <= 1.0 for g in guards) or (args.rate is not None and not 0.0 < args.rate < 1.0):
        p.error("--guards must be from 0 to 1 and --rate above 0, below 1")
    if args.workers < 1 or args.frames < 1:
        p.error("--workers and --frames must be positive")
    jobs = [(args.weights, s, args.frames) for s in args.seeds]
    with Pool(min(args.workers, len(jobs))) as pool:
        chances = np.array([c for part in pool.map(figures, jobs, chunksize=1) for c in part])
    if len(chances) == 0:
        p.error("no decision was planned (the drives ended within the warm-up)")
    print(f"{len(chances)} planned decisions on {len(jobs)} tracks; the guard's figure: median "
          f"{np.median(chances):.4f}, 99th percentile {np.quantile(chances, 0.99):.4f}")
    for g in guards:
        print(f"guard {g:g}: the candidates weigh in at {100 * np.mean(chances >= g):.2f} % of the decisions")
    if args.rate is not None:
        print(f"the guard tripped at {100 * args.rate:g} % of the decisions: {guard_for(chances, args.rate):.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The grip envelope: how fast a driver goes at each amount of steering (``control.GRIP_SPEED``).

A car steered hard at speed slides off and spins; the privileged expert never does, so the
fastest it drives with the wheels turned so far is a speed the car holds. This reads recorded
drives (an episodes file: the speed and the steering of every decision, ``actions``), bins the
decisions by the size of their steering and gives a high percentile of the speed in each bin,
made to fall as the steering grows (a bin is never faster than a less steered one):

  python -m drivesim grip --episodes data/expert.safetensors.gz

prints the bins, their decisions and speeds, and the two tuples ``control.py`` holds.
"""

from __future__ import annotations

import argparse

import numpy as np

#: Bin edges of ``|steer|``: narrow where the expert's speed changes fastest.
EDGES = (0.0, 0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
#: A bin with fewer decisions says nothing of a limit and is left out.
MIN_DECISIONS = 20


def envelope(actions: np.ndarray, quantile: float = 99.0) -> tuple[tuple, tuple, tuple]:
    """``(centres, speeds, counts)`` of the bins of ``EDGES`` holding at least ``MIN_DECISIONS``
    of ``actions`` (rows ``(speed, steer)``): the bin's centre, the ``quantile`` percentile of
    the speed in it (rounded to 0.1, at most the previous bin's) and its decisions."""
    actions = np.asarray(actions, np.float64)
    if actions.ndim != 2 or actions.shape[1] != 2 or not np.isfinite(actions).all():
        raise ValueError("actions: expected finite rows (speed, steer)")
    if not 0.0 < quantile <= 100.0:
        raise ValueError(f"quantile: expected a percentile above 0, at most 100, got {quantile}")
    speed, steer = actions[:, 0], np.abs(actions[:, 1])
    centres, speeds, counts = [], [], []
    for i, (lo, hi) in enumerate(zip(EDGES[:-1], EDGES[1:])):
        last = i == len(EDGES) - 2
        inside = (steer >= lo) & ((steer <= hi) if last else (steer < hi))
        if inside.sum() < MIN_DECISIONS:
            continue
        limit = round(float(np.percentile(speed[inside], quantile)), 1)
        centres.append(round((lo + hi) / 2, 3))
        speeds.append(min([limit] + speeds[-1:]))
        counts.append(int(inside.sum()))
    if not centres:
        raise ValueError(f"no bin of |steer| holds {MIN_DECISIONS} decisions: record more driving")
    return tuple(centres), tuple(speeds), tuple(counts)


def main(argv=None) -> int:
    from .. import episodes

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", nargs="+", required=True, help="episodes files (their actions are read)")
    p.add_argument("--quantile", type=float, default=99.0, help="the percentile of the speed in a bin")
    args = p.parse_args(argv)
    try:
        actions = np.concatenate([episodes.read(path).actions for path in args.episodes])
        centres, speeds, counts = envelope(actions, args.quantile)
    except (OSError, ValueError, episodes.EpisodesError) as e:
        raise SystemExit(f"grip: {e}") from None
    print(f"{len(actions)} decisions; the {args.quantile:g}th percentile of the speed by |steer|:")
    for centre, limit, count in zip(centres, speeds, counts):
        print(f"  |steer| ~{centre:<6g} {count:7d} decisions  {limit:6.1f} units/s")
    print(f"GRIP_STEER = {centres}\nGRIP_SPEED = {speeds}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Scores of two drivers compared track by track, from what the scoring commands printed.

``python -m drivesim.carracing`` prints a line per track (``  23000    916.0   ...``) and
``python -m drivesim record --score`` one (``seed 23000: 921.4``); save them and compare:

  python -m drivesim.carracing --agent cloned --seeds 23000-23499 --workers 2 > cloned.txt
  python -m drivesim record --score --driver expert --seeds 23000-23499 --workers 2 > expert.txt
  python -m drivesim compare cloned.txt expert.txt

For each file on the tracks both drove: the mean ± sd, the median, the worst track and the
tracks under 880 and 800; then the first less the second, its mean ± standard error and
median, the tracks where the first is ahead and where it is more than 30 behind or ahead; a
histogram of each file's scores (``BANDS``); and, per hundred tracks (``--block``), each file's
mean and its tracks under 880 and 800 (issue 61's figures: at least 915 over 100 tracks, none
under 800, at most 5 under 880).
"""

from __future__ import annotations

import argparse
import re

import numpy as np

# A track's line: the scoring command's "  23000    916.0 ..." or the recorder's "seed 23000: 921.4".
LINE = re.compile(r"\s*(?:seed\s+)?(\d+):?\s+(-?\d+(?:\.\d+)?)(?:\s|$)")


#: The histogram's band edges: the failures, then a band every 10 points about the expert's level.
BANDS = (800, 880, 900, 910, 920, 930)


def histogram(v: np.ndarray) -> str:
    """How many of the scores ``v`` fall in each band of ``BANDS``."""
    counts = np.histogram(v, [-np.inf, *BANDS, np.inf])[0]
    labels = [f"< {BANDS[0]}"] + [f"{lo}-{hi}" for lo, hi in zip(BANDS[:-1], BANDS[1:])] + [f">= {BANDS[-1]}"]
    return ", ".join(f"{label}: {n}" for label, n in zip(labels, counts))


def scores(text: str) -> dict:
    """``{track: score}`` of every track line in ``text`` (other lines skipped)."""
    found = {}
    for line in text.splitlines():
        m = LINE.match(line)
        if m:
            found[int(m.group(1))] = float(m.group(2))
    return found


def summary(v: np.ndarray) -> str:
    return (f"{v.mean():6.1f} ± {v.std(ddof=1) if len(v) > 1 else 0.0:5.1f}, median {np.median(v):6.1f}, "
            f"worst {v.min():6.1f}, under 880: {(v < 880).sum()}, under 800: {(v < 800).sum()}")


def compare(first: dict, second: dict, names=("first", "second"), block: int = 100) -> str:
    """The report (the module says what it holds) for two ``{track: score}``."""
    tracks = sorted(set(first) & set(second))
    if not tracks:
        raise ValueError("the two files have no track in common")
    a, b = (np.array([d[t] for t in tracks]) for d in (first, second))
    d = a - b
    se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
    width = max(len(n) for n in names)
    lines = [f"{len(tracks)} tracks in common"]
    lines += [f"  {n:<{width}}  {summary(v)}" for n, v in zip(names, (a, b))]
    lines.append(f"  {names[0]} - {names[1]}: {d.mean():+.1f} ± {se:.1f} (standard error), median {np.median(d):+.1f}; "
                 f"ahead on {(d > 0).sum()}, level on {(d == 0).sum()}; more than 30 behind on {(d < -30).sum()} "
                 f"{[t for t, x in zip(tracks, d) if x < -30][:10]}, ahead on {(d > 30).sum()}")
    lines += [f"  histogram of {n}: {histogram(v)}" for n, v in zip(names, (a, b))]
    starts = sorted({t // block * block for t in tracks})
    if len(starts) > 1:
        lines.append(f"  per {block} tracks: mean (under 880, under 800) of {names[0]} | {names[1]}")
        for s in starts:
            inside = [(t >= s) and (t < s + block) for t in tracks]
            cells = [f"{v[inside].mean():6.1f} ({(v[inside] < 880).sum()}, {(v[inside] < 800).sum()})" for v in (a, b)]
            lines.append(f"    {s}-{s + block - 1} ({sum(inside)}): {cells[0]} | {cells[1]}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("first", help="a scoring command's output (a line per track)")
    p.add_argument("second", help="another, for the same tracks")
    p.add_argument("--block", type=int, default=100, help="tracks per block in the per-block table")
    args = p.parse_args(argv)
    if args.block < 1:
        p.error("--block must be positive")
    try:
        found = []
        for path in (args.first, args.second):
            with open(path, encoding="utf-8") as f:
                found.append(scores(f.read()))
        print(compare(*found, names=(args.first, args.second), block=args.block))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise SystemExit(f"compare: {e}") from None
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

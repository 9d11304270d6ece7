"""Each driver's off-road gap, dreamt against real, pooled over the tracks of several rank reports
of one family (``python -m drivesim.carracing.rank``'s ``rank.json``): with 20 tracks a set a
gap's standard error is 1 to 3 points of share; pooled over 60 it is under 1, enough to tell a
gap just past the issue's 0.1 from one at it (docs/history/gap_error.md).

  python -m drivesim.carracing.rank_pool runs/a/rank.json runs/b/rank.json [--whole] [--report pooled.json]

The windows' figures are pooled (``--whole``: the whole drives'): each report's per-track shares
(``off_road_per_track``) are put side by side, the gap's standard error paired by track as `rank`
reports it (`rank_figures.off_road_gaps`). The reports must name the same drivers in the same
order, be dreamt alike (`DREAMT_ALIKE`: the same drivers' weights, world, judge, futures and how
their off-road shares are read), and no track may be in two of them (it would count twice).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from .._files import atomic_write
from .rank_figures import SHARE_GAP, off_road_gaps


#: The settings of a rank report that change its shares: reports pooled must agree on each (a
#: report made before `rank` wrote ``off_road_read`` read its futures' mean).
DREAMT_ALIKE = {"weights": None, "world": None, "judge": None, "horizon": None, "starts": None, "frames": None,
                "temperature": None, "futures": None, "off_road_read": "mean", "world_steering": None,
                "through_frames": None}


def settings_of(report: dict) -> dict:
    """The `DREAMT_ALIKE` settings of a rank report, those it lacks at their defaults."""
    return {key: report.get(key, default) for key, default in DREAMT_ALIKE.items()}


def read_report(path: str, whole: bool) -> tuple[list, list, np.ndarray, np.ndarray, dict]:
    """The drivers' names, the tracks, the real and dreamt off-road shares ``(drivers, tracks)``
    of the rank report ``path`` (its windows' figures, or with ``whole`` its whole drives') and its
    `settings_of`; ValueError naming what is wrong."""
    try:
        with open(path, encoding="utf-8") as f:
            report = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable rank report ({e})") from None
    figures = report if whole else report.get("windows") if isinstance(report, dict) else None
    if not isinstance(figures, dict):
        raise ValueError(f"{path}: no {'whole drives' if whole else 'windows (a rank run with --windows)'} in it")
    if "off_road_per_track" not in figures:
        raise ValueError(f"{path}: made before rank kept each track's shares; run rank again with the same --out "
                         "(the real drives are kept: seconds)")
    try:
        names = [d["driver"]["name"] for d in figures["drivers"]]
        shares = [np.asarray(figures["off_road_per_track"][k], float) for k in ("real", "dream")]
        tracks = [int(s) for s in report["seeds"]]
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a rank report ({e!r} is missing or malformed)") from None
    if not tracks:
        raise ValueError(f"{path}: it names no tracks")
    if any(s.shape != (len(names), len(tracks)) or not np.isfinite(s).all() for s in shares):
        raise ValueError(f"{path}: its shares are not one finite number for each driver and track")
    return names, tracks, shares[0], shares[1], settings_of(report)


def pooled(paths: list, whole: bool = False) -> dict:
    """The pooled figures of the reports ``paths``: each driver's real and dreamt share, its gap
    and the gap's standard error over all their tracks, ``within`` (gaps within ``SHARE_GAP``) and
    ``shown_outside`` (beyond it by more than two standard errors)."""
    names, tracks, real, dream, settings = read_report(paths[0], whole)
    for path in paths[1:]:
        other, more, r, d, its = read_report(path, whole)
        if other != names:
            raise ValueError(f"{path}: another family's drivers than {paths[0]}'s")
        differ = [key for key in DREAMT_ALIKE if its[key] != settings[key]]
        if differ:
            key = differ[0]
            raise ValueError(f"{path}: dreamt otherwise than {paths[0]} ({key} {its[key]!r}, not {settings[key]!r})")
        if set(more) & set(tracks):
            raise ValueError(f"{path}: tracks {sorted(set(more) & set(tracks))} are in another report too")
        tracks, real, dream = tracks + more, np.concatenate([real, r], 1), np.concatenate([dream, d], 1)
    gap, se, within, shown_outside = off_road_gaps(real, dream)
    return {"reports": list(paths), "tracks": len(tracks), "whole": whole, "within": within,
            "shown_outside": shown_outside,
            "drivers": [{"driver": n, "real_off_road": float(real[i].mean()), "dream_off_road": float(dream[i].mean()),
                         "gap": float(gap[i]), "gap_se": float(se[i])} for i, n in enumerate(names)]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing.rank_pool", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reports", nargs="+", help="rank reports (rank.json) of one family on different tracks")
    p.add_argument("--whole", action="store_true", help="pool the whole drives' figures, not the windows'")
    p.add_argument("--report", help="a JSON file for the pooled figures")
    args = p.parse_args(argv)
    try:
        out = pooled(args.reports, args.whole)
    except ValueError as e:
        p.error(str(e))
    print(f"{'driver':28} {'real':>7} {'dream':>7} {'gap':>7} {'± se':>6}")
    for d in out["drivers"]:
        print(f"{d['driver']:28} {d['real_off_road']:7.1%} {d['dream_off_road']:7.1%} {d['gap']:+7.1%} ±{d['gap_se']:5.1%}")
    print(f"{out['tracks']} tracks: within {SHARE_GAP} of the real share {out['within']} of {len(out['drivers'])} drivers; "
          f"outside it by more than two standard errors (paired by track) {out['shown_outside']}")
    if args.report:
        with atomic_write(args.report) as f:
            f.write(json.dumps(out, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The rank probe's figures (`drivesim.carracing.rank`): Spearman, regret@1 and Pearson of the
dream's scores against the real ones over a family of drivers, each driver's off-road shares,
and, where the dream drew several futures from each start, how far they disagree (the dream's
own doubt) and whether it doubts most where it is wrong; and the printed report."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from .family import Driver

# The bound on a driver's off-road share, dream against real, and the bound proposed for a
# steady pull, in steering: on the cliff a hundredth of steering moves the real share by 0.1 or more.
SHARE_GAP, PULL_GAP = 0.1, 0.03

# Decisions the dream knows the real road for (the view's reach: docs/judging.md); the unchanged
# driver's steering after them is on roads the dream makes up.
MEMORY = 10


def ranks(x: np.ndarray) -> np.ndarray:
    """Ranks from 0, ties sharing their mean rank."""
    order = np.argsort(x, kind="stable")
    r = np.empty(len(x))
    r[order] = np.arange(len(x))
    for value in np.unique(x):
        tied = x == value
        r[tied] = r[tied].mean()
    return r


def spearman(a, b) -> float:
    a, b = ranks(np.asarray(a, float)), ranks(np.asarray(b, float))
    if a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def pearson(a, b) -> float:
    """The Pearson correlation of ``a`` and ``b``; NaN where either does not vary."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else float("nan")


def road_memory(dreamt: np.ndarray, real: np.ndarray) -> list:
    """How far ahead the dream knows the road: the correlation, step by step, of the unchanged
    driver's steering in the dream with its real steering from the same starts (``(starts,
    horizon)`` each; the policy steers by the road it sees, so where the dream's road is not the
    real one the two part). NaN at a step where either does not vary."""
    out = []
    for a, b in zip(dreamt.T, real.T):
        out.append(float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else float("nan"))
    return out


# Steering past this either way is the unchanged driver following a bend (docs/history/coming_back.md).
BEND = 0.05


def made_up_roads(dreamt: np.ndarray, real: np.ndarray, after: int = MEMORY) -> dict | None:
    """How the unchanged driver steers on the roads the dream makes up once its road memory is
    spent (from decision ``after`` on; ``(starts, horizon)`` steerings each, as `road_memory`):
    its mean absolute steering, mean change of steering a decision, and the shares of decisions
    in a bend to the left and to the right (steering past ``BEND``), in the dream and on the real
    road from the same starts. The policy steers by the road it sees, so the two agree where the
    made-up roads are as curvy, as steady and as often bent each way as the real ones (CarRacing's
    laps bend left about twice as often; a pull leaves in bends of its own side: docs/judging.md).
    None for a horizon too short to have a decision past ``after``."""
    if dreamt.shape[1] < after + 2:
        return None
    a, b = dreamt[:, after:], real[:, after:]
    return dict(after=after, dream=float(np.abs(a).mean()), real=float(np.abs(b).mean()),
                dream_change=float(np.abs(np.diff(a, axis=1)).mean()), real_change=float(np.abs(np.diff(b, axis=1)).mean()),
                dream_left=float((a < -BEND).mean()), real_left=float((b < -BEND).mean()),
                dream_right=float((a > BEND).mean()), real_right=float((b > BEND).mean()))


def equivalent_pulls(family: list, real_off: np.ndarray, dream_off: np.ndarray) -> list:
    """For each driver of ``family`` whose one change is a steady pull (``bias``): the pull at
    which the real car is off the road as often as the dream has this driver off (``real_off``,
    ``dream_off``: each driver's mean share), read off the real curve of the family's pulls on that
    side, the unchanged driver at 0 (linear between them, made non-decreasing). Near a cliff the
    real share jumps with a hundredth of steering, and a gap in shares says little; a gap in pulls
    says how far early or late the dream lets go (docs/judging.md). ``equivalent`` is None where the
    dreamt share is beyond the real curve's ends. Empty for a family with no pulls."""
    pulls = {i: d.bias for i, d in enumerate(family) if d == Driver(d.name, bias=d.bias)}
    out = []
    for side in (1.0, -1.0):
        points = sorted((abs(b), real_off[i]) for i, b in pulls.items() if b * side >= 0)
        x = np.array([p[0] for p in points])
        curve = np.maximum.accumulate([p[1] for p in points])
        for i, b in pulls.items():
            if b * side <= 0 or len(x) < 2:
                continue
            found = None
            for j in range(len(x) - 1):  # every point of the curve at the dreamt share; the nearest
                lo, hi, d = curve[j], curve[j + 1], dream_off[i]
                if not lo <= d <= hi:
                    continue
                at = np.clip(abs(b), x[j], x[j + 1]) if lo == hi else x[j] + (d - lo) / (hi - lo) * (x[j + 1] - x[j])
                if found is None or abs(at - abs(b)) < abs(found - abs(b)):
                    found = float(at)
            out.append({"driver": family[i].name, "pull": float(b), "real_off_road": float(real_off[i]),
                        "dream_off_road": float(dream_off[i]),
                        "equivalent": None if found is None else side * found})
    return out


def leaving_counts(off: np.ndarray, memory: int = MEMORY) -> np.ndarray:
    """Whether the car comes back once it has left the road, from off-road flags ``(drivers,
    windows, horizon)`` (the dream's: its off-road chance above one half), per driver ``(drivers,
    8)``: the windows, those in which the car leaves the road, the decisions from each first
    leaving on and how many of them it is off; then the decisions of the ``memory`` after a first
    leaving within the view's reach (the first ``memory`` decisions, where the dream knows the
    road) and how many of them it is off, and the same after a first leaving past it (on roads
    the dream makes up). They add over tracks and futures (`leaving`)."""
    off = np.asarray(off) > 0.5
    horizon = off.shape[2]
    ever = off.any(2)
    first = np.where(ever, off.argmax(2), horizon)
    step = np.arange(horizon)
    after = step >= first[..., None]
    soon = after & (step < first[..., None] + memory)
    in_view = (first < memory)[..., None]
    columns = [np.ones_like(ever), ever, after, off & after, soon & in_view, off & soon & in_view,
               soon & ~in_view, off & soon & ~in_view]
    return np.stack([c.reshape(len(off), -1).sum(1) for c in columns], 1).astype(float)


def bend_sums(off: np.ndarray, road: np.ndarray, before: int = 5) -> np.ndarray:
    """Which way the road bends where the real car first leaves it: ``off`` ``(drivers, windows,
    horizon)`` the real windows' flags, ``road`` ``(windows, horizon)`` the behaviour drive's
    steering over the same decisions (the unchanged driver steers with the road); per driver the
    sum over the windows that leave of the mean steering over the ``before`` decisions up to the
    first leaving, and their count ``(drivers, 2)``."""
    off = np.asarray(off) > 0.5
    out = np.zeros((len(off), 2))
    for i, j in zip(*np.nonzero(off.any(2))):
        t = int(off[i, j].argmax())
        out[i] += (road[j, max(t - before, 0):t + 1].mean(), 1)
    return out


def leaving(family: list, real: np.ndarray, dreamt: np.ndarray, bends: np.ndarray, road: float,
            memory: int = MEMORY) -> dict:
    """Each driver's share of windows in which the car leaves the road, real and dreamt, its share
    of decisions off the road from then on, and of the ``memory`` decisions after a first leaving
    within the view's reach and past it (None where there is none), from `leaving_counts` (of the
    same ``memory``) summed over tracks (and the dream's futures); and the road's bend where the
    real car leaves (`bend_sums`), against ``road``, the behaviour drive's mean steering over all
    the windows."""
    def shares(c):
        ratio = lambda n, d: float(n / d) if d else None
        return {"leaves": float(c[1] / c[0]), "off_after": ratio(c[3], c[2]),
                "off_after_in_view": ratio(c[5], c[4]), "off_after_past_view": ratio(c[7], c[6])}
    return {"road_steering": float(road), "memory": memory, "drivers": [
        {"driver": d.name, "real": shares(real[i]), "dream": shares(dreamt[i]),
         "bend_where_real_leaves": float(bends[i, 0] / bends[i, 1]) if bends[i, 1] else None}
        for i, d in enumerate(family)]}


def off_road_gap_error(real_off: np.ndarray, dream_off: np.ndarray) -> np.ndarray:
    """The standard error of each driver's off-road gap, dreamt against real, paired by track
    (``(drivers, tracks)`` shares each): the tracks' spread of the gap over the square root of their
    number (a track's windows share its bends, so the track, not the window, is the unit). NaN with
    one track."""
    diff = np.asarray(dream_off, float) - np.asarray(real_off, float)
    if diff.shape[1] < 2:
        return np.full(len(diff), np.nan)
    return diff.std(1, ddof=1) / np.sqrt(diff.shape[1])


def off_road_gaps(real_off: np.ndarray, dream_off: np.ndarray) -> tuple:
    """From ``(drivers, tracks)`` shares: each driver's off-road gap (its dreamt share less its
    real one, over the tracks) and the gap's standard error (`off_road_gap_error`), and how many
    gaps are within ``SHARE_GAP`` and how many beyond it by more than two standard errors (a gap
    the tracks' own spread cannot explain)."""
    gap = np.asarray(dream_off, float).mean(1) - np.asarray(real_off, float).mean(1)
    se = off_road_gap_error(real_off, dream_off)
    return gap, se, int((np.abs(gap) <= SHARE_GAP).sum()), int((np.abs(gap) - 2 * se > SHARE_GAP).sum())


def summary(family: list, real: np.ndarray, real_off: np.ndarray, dreamt: np.ndarray, dream_off: np.ndarray,
            spread: np.ndarray | None = None) -> dict:
    """The figures of the report from ``(drivers, tracks)`` arrays of real scores and off-road
    shares, and the dream's returns and off-road chances (each the mean over the starts and the
    futures). ``spread`` (with several futures a start): ``(2, drivers, tracks)``, the standard
    deviation over the futures of a start's return and of its off-road chance, averaged over the
    starts; each driver gets their means, and ``doubt_against_error`` is the Pearson correlation
    over the family of the return's spread with the dream's error in ranks, |its rank in the
    dream - its real rank|. Each driver's off-road gap comes with its standard error, paired by
    track (`off_road_gap_error`), and ``shown_outside`` counts the drivers whose gap is beyond
    ``SHARE_GAP`` by more than two of them."""
    real_mean, dream_mean = real.mean(1), dreamt.mean(1)
    favourite = int(np.argmax(dream_mean))
    span = real_mean.max() - real_mean.min()
    per_track = [spearman(dreamt[:, t], real[:, t]) for t in range(real.shape[1])]
    gap, gap_se, within, shown_outside = off_road_gaps(real_off, dream_off)
    gap = np.abs(gap)
    out = {
        "spearman": spearman(dream_mean, real_mean),
        "spearman_per_track": float(np.nanmean(per_track)),
        "regret_at_1": float((real_mean.max() - real_mean[favourite]) / span) if span > 0 else 0.0,
        "pearson": pearson(dream_mean, real_mean),
        "off_road_gap": float(gap.max()),
        "favourite": family[favourite].name,
        "pulls": equivalent_pulls(family, real_off.mean(1), dream_off.mean(1)),
        "within": within,
        "shown_outside": shown_outside,
        "drivers": [{"driver": asdict(d), "real": float(real_mean[i]), "real_sd": float(real[i].std()),
                     "real_off_road": float(real_off[i].mean()), "dream": float(dream_mean[i]),
                     "dream_off_road": float(dream_off[i].mean()), "off_road_gap_se": float(gap_se[i])}
                    for i, d in enumerate(family)],
        "off_road_per_track": {"real": real_off.tolist(), "dream": dream_off.tolist()},
    }
    near = {p["driver"] for p in out["pulls"]
            if p["equivalent"] is not None and abs(p["equivalent"] - p["pull"]) <= PULL_GAP}
    out["within_or_pull"] = sum(bool(g <= SHARE_GAP or d.name in near) for g, d in zip(gap, family))
    if spread is not None:
        doubt = spread.mean(2)
        for i, d in enumerate(out["drivers"]):
            d["dream_spread"], d["dream_off_road_spread"] = float(doubt[0, i]), float(doubt[1, i])
        # The error in ranks: a whole drive's score and a dream's 40 decisions are not one scale.
        out["doubt_against_error"] = pearson(doubt[0], np.abs(ranks(dream_mean) - ranks(real_mean)))
    return out


def doubt(figures: dict) -> str:
    """A driver's (or the family's) spread over the dream's futures, for the printed tables
    (nothing where the dream drew one future)."""
    if "dream_spread" in figures:
        return f" {figures['dream_spread']:>8.1f} {figures['dream_off_road_spread']:>8.1%}"
    if "doubt_against_error" in figures:
        return f"; the futures' spread against the dream's error in ranks: Pearson {figures['doubt_against_error']:+.2f}"
    return ""


def gap_text(figures: dict) -> str:
    """A driver's off-road gap, dreamt less real, and its standard error, for the printed tables."""
    return f" {figures['dream_off_road'] - figures['real_off_road']:+7.1%} ±{figures['off_road_gap_se']:5.1%}"


def print_pulls(pulls: list) -> None:
    """The steady pulls' lines: each dreamt share as the pull the real car needs for it."""
    if pulls:
        print("\nsteady pulls, the dream's share of decisions off the road read as the pull that takes the real car "
              "off as often:")
    for p in pulls:
        e = p["equivalent"]
        said = ("beyond the real pulls'" if e is None else
                f"the real car's at {e:+.3f} ({abs(e) - abs(p['pull']):+.3f} in strength)")
        print(f"{p['driver']:24} dreamt off the road {p['dream_off_road']:.0%} (real {p['real_off_road']:.0%}): {said}")


def print_leaving(figures: dict) -> None:
    """The lines of `leaving`: whether the car, once off the road, comes back."""
    m = figures["memory"]
    print(f"\nleaving the road and coming back (windows): the share of windows the car leaves the road in; "
          f"of the decisions from then on, and of the {m} after it leaves within the view's first {m} or past them, "
          f"those off the road; the road's bend (the behaviour drive's steering, {figures['road_steering']:+.3f} on "
          f"average) where the real car leaves it. Real / dream:\n"
          f"{'driver':24} {'leaves':>11} {'off after':>11} {'in view':>11} {'past view':>11} {'bend':>7}")
    pct = lambda x: "  -" if x is None else f"{x:3.0%}"
    for d in figures["drivers"]:
        r, e, bend = d["real"], d["dream"], d["bend_where_real_leaves"]
        print(f"{d['driver']:24}" + "".join(f" {pct(r[k]):>4} / {pct(e[k]):>4}" for k in
                                            ("leaves", "off_after", "off_after_in_view", "off_after_past_view"))
              + f" {'-' if bend is None else f'{bend:+.3f}':>7}")


def print_report(out: dict) -> None:
    spread = f" {'± spread':>8} {'off road':>8}" if "doubt_against_error" in out else ""
    gaps = f" {'gap':>7} {'± se':>6}"
    print(f"\n{'driver':24} {'real':>8} {'± sd':>6} {'off road':>8} {'dream':>8} {'off road':>8}{gaps}{spread}")
    for d in out["drivers"]:
        print(f"{d['driver']['name']:24} {d['real']:8.1f} {d['real_sd']:6.1f} {d['real_off_road']:8.1%} "
              f"{d['dream']:8.1f} {d['dream_off_road']:8.1%}{gap_text(d)}{doubt(d)}")
    print(f"Spearman {out['spearman']:+.2f} over the family ({out['spearman_per_track']:+.2f} per track, averaged); "
          f"regret@1 {out['regret_at_1']:.2f} (the dream's favourite: {out['favourite']}); Pearson {out['pearson']:+.2f}; "
          f"the largest off-road gap {out['off_road_gap']:.2f}; {len(out['seeds'])} tracks, {out['starts']} starts, "
          f"horizon {out['horizon']}; {out['dream_decisions_per_second']:.0f} dream decisions a second{doubt(out)}")
    if "windows" in out:
        w = out["windows"]
        print(f"\nthe same starts in the real env, {out['horizon']} decisions each (the dream without the value):")
        print(f"{'driver':24} {'real':>8} {'off road':>8} {'dream':>8} {'off road':>8}{gaps}{spread}")
        for d in w["drivers"]:
            print(f"{d['driver']['name']:24} {d['real']:8.1f} {d['real_off_road']:8.1%} {d['dream']:8.1f} "
                  f"{d['dream_off_road']:8.1%}{gap_text(d)}{doubt(d)}")
        steps = [s for s in (5, 10, 20) if s < out["horizon"]] + [out["horizon"]]  # the last always shown
        print("\noff the road at decision N of the windows, real / dream / the dream given the real window's "
              "actions (open loop):\n" + f"{'driver':24}" + "".join(f"{s:>18}" for s in steps))
        by = w["off_by_decision"]
        for d, real, dream, given in zip(w["drivers"], by["real"], by["dream"], by["open_loop"]):
            print(f"{d['driver']['name']:24}"
                  + "".join(f"{real[s - 1]:>6.0%} /{dream[s - 1]:>4.0%} /{given[s - 1]:>4.0%}" for s in steps))
        if "leaving" in w:
            print_leaving(w["leaving"])
        print_pulls(w["pulls"])
        print(f"windows: Spearman {w['spearman']:+.2f} ({w['spearman_per_track']:+.2f} per track); regret@1 "
              f"{w['regret_at_1']:.2f} ({w['favourite']}); Pearson {w['pearson']:+.2f}; the largest off-road gap "
              f"{w['off_road_gap']:.2f}; within {SHARE_GAP} of the real share {w['within']} of {len(w['drivers'])} "
              f"drivers, or a pull within {PULL_GAP} of steering {w['within_or_pull']}; outside it by more than two "
              f"standard errors (paired by track) {w['shown_outside']}{doubt(w)}")
    if "road_memory" in out:
        steps = [s for s in (1, 3, 5, 8, 10, 20, 40) if s <= len(out["road_memory"])]
        print("road memory (the unchanged driver's steering, dream against real, correlation after N decisions): "
              + ", ".join(f"{s}: {out['road_memory'][s - 1]:+.2f}" for s in steps))
    if out.get("made_up_roads"):
        m = out["made_up_roads"]
        print(f"made-up roads (the unchanged driver from decision {m['after'] + 1} on, dream / real): mean |steering| "
              f"{m['dream']:.3f} / {m['real']:.3f}, its change a decision {m['dream_change']:.3f} / {m['real_change']:.3f}; "
              f"in a bend left {m['dream_left']:.0%} / {m['real_left']:.0%}, right {m['dream_right']:.0%} / {m['real_right']:.0%}")

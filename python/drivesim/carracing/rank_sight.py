"""Where the car is when it is off the road, in the real windows and in the dream's from the same
starts (``python -m drivesim.carracing.rank``'s): the real car that leaves the road mostly rides
its edge, with the road in sight; a dream whose roads end leaves its car in a field with none
(docs/history/reach.md; docs/judging.md, "Trades, reach, and roads that do not end: the judge").

  python -m drivesim.carracing.rank_sight --seeds 14700-14719 --out runs/rank --drivers 0,3 [--temperature 0.9]

``--out`` is a rank run's folder (its behaviour drives, ``drive_SEED.npz``, are read, and its
``drivers.json`` must name the same drivers; ``--report`` names the one file written). For each
driver of the family (by index), each track and each start, the real window is driven again with
its frames kept, and the dream's is dreamt as ``rank`` dreams it (``--weights`` the drivers,
``--world`` the world, ``--judge`` its futures drawn by the judge's sampler and its steering
`rank.JUDGE_STEERING` at `rank.JUDGE_TEMPERATURE`, ``--world-steering`` the world's steering
shaped as ``rank``'s, one future, the same noise seeds);
every frame a driver read is measured (`sight`), and the report gives, over bins of ``--every``
decisions, the share of decisions off the road (the real car's: no wheel on it; the
dream's: its reward head's chance), of frames with road in sight, of frames with road just ahead
of the car, and of the off-road decisions' frames with road in sight; and, from the first decision
past the view's reach on, that share by how long ago the car left the road (`sight_since_leaving`:
the real car that leaves keeps the road in sight; a dream that loses it keeps its car off), and by
where across the road the car is, read off the frame (`across`), how often the road is gone from
beside the car the next decision (`road_beside`: the real road stays until the car is far off it;
the judge's is lost at the edge, docs/history/road_at_the_edge.md). The real side adds
``head_on_real``: the world's reward head's off-road chance on the real window's own states (its
frames through the world's encoder, the world's hidden state stepped on them with the real inputs
from the start's): where it matches the real share and the dream's does not, the dream's gap is
its trajectory, not its head (docs/judging.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from .. import road
from .._batches import batched
from .._drivesim import Simulator
from .._files import atomic_write
from . import rank, rank_dream, rank_real
from .family import FAMILY
from .rank_figures import MEMORY
from .view import parse_seeds

# The car's box in the 80x160 view (its sprite has road-grey pixels) and the band just ahead of it.
CAR_BOX = (slice(58, 76), slice(70, 90))
AHEAD = (slice(48, 58), slice(60, 100))
# Bins of decisions since the car left the road (`sight_since_leaving`); None: to the horizon.
SINCE_BINS = ((0, 0), (1, 2), (3, 5), (6, 10), (11, None))
# `across`: the rows of the car and the band just ahead, where the road's centre is read; the pixels
# a half-road spans there (real frames' road centre against the env's centre line, 0.89 correlated;
# docs/history/road_at_the_edge.md); fewer road pixels than ROAD_PIXELS there and the road is gone
# from beside the car (in real frames only once the car is 2 to 3 half-roads off it).
CAR_ROWS, HALF_ROAD_PX, ROAD_PIXELS = slice(52, 70), 19.8, 20
# Bins of where across the road the car is (`road_beside`), in half-roads from its centre, + left:
# from about 1.25 out its wheels are off the road.
PLACES = (-1.5, -1.25, -1.0, -0.5, 0.5, 1.0, 1.25, 1.5)


def sight(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For uint8 frames ``(N, 80, 160, 3)``: whether any road pixel is in sight outside the car's
    box, and whether road lies in the 10 rows ahead of the car within 20 px of it; bool ``(N,)`` each."""
    mask = road.road_mask(frames)
    mask[(slice(None), *CAR_BOX)] = False
    ahead = mask[(slice(None), *AHEAD)]
    return mask.reshape(len(frames), -1).any(1), ahead.reshape(len(frames), -1).any(1)


def across(frames: np.ndarray) -> np.ndarray:
    """Where across the road the car is in each uint8 frame ``(N, 80, 160, 3)``, in half-roads
    from the road's centre (+: the car left of it): the mean column of the road pixels in the
    car's rows, its sprite left out; NaN where the road is gone from beside the car."""
    mask = road.road_mask(frames)[:, CAR_ROWS]
    mask[:, CAR_BOX[0].start - CAR_ROWS.start:, CAR_BOX[1]] = False
    count = mask.sum((1, 2))
    centre = (mask * np.arange(mask.shape[2])).sum((1, 2)) / np.maximum(count, 1)
    return np.where(count >= ROAD_PIXELS, (centre - mask.shape[2] / 2) / HALF_ROAD_PX, np.nan)


def head_on_frames(world: Simulator, frames: np.ndarray, inputs: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The world's off-road chance of each state a real window showed: ``frames`` ``(N, 80, 160,
    3)`` through the world's encoder, its hidden state from ``h`` (the start's) stepped on each
    code with the window's ``inputs`` ``(N, 2)`` (the speed and the steering applied), the reward
    head on each code with the hidden state it was seen in (as `rank_dream.dream` scores its steps)."""
    codes = batched(world.encode, frames, world.batch)
    states = [np.asarray(h, np.float32)[None]]
    for t in range(len(frames) - 1):
        states.append(world.transition(codes[t:t + 1], states[-1], np.ascontiguousarray(inputs[t:t + 1], np.float32))[1])
    return batched(lambda z, h: world.reward(z, h)[:, 1], codes, world.batch, np.concatenate(states))


def real_windows(drive: dict, seed: int, index: int, args, world: Simulator, starts: dict) -> np.ndarray:
    """Driver ``index``'s real windows on track ``seed`` (`rank_real.drive_windows`, as a rank run
    drives them), its frames measured: ``(5, starts, horizon)``, the off-road flags, road in sight,
    road ahead, the car's place (`across`) and the world's off-road chance of each state
    (`head_on_frames` from ``starts``'s hidden states; a window the episode's end cut short keeps
    its last to the horizon)."""
    out = []
    windows = rank_real.drive_windows(drive, FAMILY[index], index, seed, args, frames=True)
    for j, (_, flags, inputs, seen) in enumerate(windows):
        frames = np.stack(seen)
        in_sight, ahead = sight(frames)
        inputs = np.array(inputs, np.float32)  # the world steps with the steering as a dream does
        before = np.concatenate([starts["previous"][j:j + 1], inputs[:-1, 1]])
        shaped = rank_dream.world_steering(inputs, before, args.world_steering)
        head = head_on_frames(world, frames, shaped, starts["h_world"][j])
        rows = [[float(f) for f in flags], in_sight.tolist(), ahead.tolist(), across(frames).tolist(), head.tolist()]
        out.append(rank_real.padded_to_horizon(rows, args.horizon))
    return np.stack(out, 1)


def figures(measured: np.ndarray, every: int) -> list:
    """Per bin of ``every`` decisions: off the road, road in sight, road ahead, and road in sight
    where off (``measured`` ``(rows, windows, horizon)``: off-road flags or chances, `sight`'s two
    figures, `across`'s place, and for the real windows a fifth row, the world's chance on their
    states, as ``head_on_real``); None where no decision of a bin is off the road."""
    off, seen, ahead = measured[0], measured[1] > 0.5, measured[2] > 0.5
    horizon = off.shape[1]
    out = []
    for a in range(0, horizon, every):
        o, s, h = off[:, a:a + every], seen[:, a:a + every], ahead[:, a:a + every]
        gone = o > 0.5
        out.append({"decisions": [a + 1, min(a + every, horizon)], "off_road": float(o.mean()),
                    "in_sight": float(s.mean()), "ahead": float(h.mean()),
                    "in_sight_where_off": float(s[gone].mean()) if gone.any() else None})
        if len(measured) > 4:
            out[-1]["head_on_real"] = float(measured[4][:, a:a + every].mean())
    return out


def since_leaving(off: np.ndarray) -> np.ndarray:
    """For off-road flags ``off`` ``(windows, horizon)``: at each decision off the road, how many
    decisions ago the car left it (0 at the first decision off), and -1 on the road."""
    since = np.full(off.shape, -1)
    for t in range(off.shape[1]):
        before = since[:, t - 1] if t else np.full(len(off), -1)
        since[:, t] = np.where(off[:, t], before + 1, -1)
    return since


def sight_since_leaving(measured: np.ndarray, first: int = MEMORY) -> list:
    """The share of off-road frames with road in sight from decision ``first`` on (past the view's
    reach: on made-up roads), by how long ago the car left the road (`SINCE_BINS`; ``measured`` as
    `figures` takes it): the real car that leaves rides the road's edge and steers back to it; a
    dream that loses the road once its car is off keeps the car off (docs/history/road_in_sight.md).
    Each bin: the decisions since leaving, the frames counted, and the share (None where none)."""
    since = since_leaving(measured[0] > 0.5)
    since[:, :first] = -1
    seen = measured[1] > 0.5
    out = []
    for lo, hi in SINCE_BINS:
        cell = (since >= lo) & (since <= (hi if hi is not None else since.max()))
        out.append({"since": [lo, hi], "frames": int(cell.sum()),
                    "in_sight": float(seen[cell].mean()) if cell.any() else None})
    return out


def road_beside(measured: np.ndarray, first: int = MEMORY) -> dict:
    """From decision ``first`` on (``measured`` as `figures` takes it): by where across the road
    the car is (`PLACES`' bins of `across`), the decisions, their off-road share, and the share
    after which the road is gone from beside the car the next decision (``lost``: the real road
    stays until the car is far off it; a dream that loses it at the edge keeps its car off,
    docs/history/road_at_the_edge.md); and the share of decisions with the road gone, and theirs off
    the road. None where a bin has no decision."""
    off, place = measured[0][:, first:], measured[3][:, first:]
    now, bins = place[:, :-1], np.digitize(place[:, :-1], PLACES)
    gone_next = np.isnan(place[:, 1:])
    edges = (None, *PLACES, None)
    out = []
    for i in range(len(PLACES) + 1):
        cell = (bins == i) & ~np.isnan(now)
        out.append({"place": [edges[i], edges[i + 1]], "decisions": int(cell.sum()),
                    "off_road": float(off[:, :-1][cell].mean()) if cell.any() else None,
                    "lost": float(gone_next[cell].mean()) if cell.any() else None})
    gone = np.isnan(place)
    return {"places": out, "gone": float(gone.mean()) if gone.size else None,
            "off_road_where_gone": float(off[gone].mean()) if gone.any() else None}


def since_label(lo: int, hi: int | None) -> str:
    """A `SINCE_BINS` bin as printed: ``0``, ``1-2``, ``11-``."""
    return str(lo) if hi == lo else f"{lo}-{'' if hi is None else hi}"


def place_label(lo: float | None, hi: float | None) -> str:
    """A `PLACES` bin as printed: ``<-1.5``, ``-1.0..-0.5``, ``>1.5``."""
    return f"<{hi}" if lo is None else f">{lo}" if hi is None else f"{lo}..{hi}"


def share(x: float | None) -> str:
    """A share as printed, ``-`` for None."""
    return "-" if x is None else f"{x:.2f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing.rank_sight", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=parse_seeds, required=True, help="track seeds of the rank run, e.g. 14700-14719")
    p.add_argument("--out", required=True, help="the rank run's folder (its drive_SEED.npz are read)")
    p.add_argument("--drivers", default="0", help="the family's drivers by index (family.FAMILY), e.g. 0,3,4")
    p.add_argument("--weights", help="the drivers' weight file, as the rank run's (default: the built-in model)")
    p.add_argument("--world", help="the world model's weight file (default: --weights)")
    p.add_argument("--judge", action="store_true",
                   help="the world's futures drawn by the built-in judge (Model.judge), stepped as `rank --judge` does")
    p.add_argument("--temperature", type=float,
                   help="the dream's (0: the mean dream; default 0.9, with --judge rank.JUDGE_TEMPERATURE)")
    p.add_argument("--world-steering", type=rank.shaping, metavar="GAIN[,LEAD]",
                   help="the world steps with GAIN x each steering and LEAD x its change, held at full lock "
                        "(default 1, with --judge rank.JUDGE_STEERING)")
    p.add_argument("--horizon", type=int, default=40)
    p.add_argument("--starts", type=int, default=7)
    p.add_argument("--every", type=int, default=10, help="decisions a bin of the report")
    p.add_argument("--frames", type=int, default=1000, help="env frames a drive, as the rank run's")
    p.add_argument("--report", help="a JSON file for the figures")
    args = p.parse_args(argv)
    try:
        drivers = [int(x) for x in args.drivers.split(",")]
        if not all(0 <= i < len(FAMILY) for i in drivers):
            raise ValueError
    except ValueError:
        p.error(f"--drivers: indices of family.FAMILY from 0 to {len(FAMILY) - 1}, e.g. 0,3, got {args.drivers!r}")
    rank.dream_settings(args, {"world_steering": (1.0, 0.0), "temperature": 0.9})  # one future, as `rank`'s first
    if args.horizon < 1 or args.starts < 1 or args.every < 1 or not 0 <= args.temperature <= 100:
        p.error("--horizon, --starts and --every must be at least 1, --temperature from 0 to 100")
    if args.judge and args.temperature == 0:
        p.error("--judge needs --temperature above 0: the mean dream draws no futures")
    missing = [s for s in args.seeds if not os.path.exists(os.path.join(args.out, f"drive_{s}.npz"))]
    if missing:
        p.error(f"{args.out} has no behaviour drive of track {missing[0]}: run `python -m drivesim.carracing.rank` "
                "with this --out and these --seeds first")
    driver_model = rank.load_model(p, "--weights", args.weights)
    world_model = rank.load_model(p, "--world" if args.world else "--judge", args.world or args.weights, args.judge) \
        if args.world or args.judge else driver_model
    try:  # the behaviour drives hold these drivers' memory: another policy's would not do
        rank_real.check_drivers(args.out, rank_real.drivers_fingerprint(driver_model))
        for seed in args.seeds:
            with np.load(os.path.join(args.out, f"drive_{seed}.npz")) as f:
                rank_dream.window_starts({k: f[k] for k in ("first", "speed")}, args.starts, args.horizon)
    except (OSError, ValueError, KeyError) as e:
        p.error(f"{args.out}: {e}")
    family = [FAMILY[i] for i in drivers]
    batch = len(family) * args.starts
    driver, world = Simulator(driver_model, batch=batch), Simulator(world_model, batch=batch)
    if args.temperature > 0:
        world.set_sampling(args.temperature, 0)
    real, dreamt = [[] for _ in family], [[] for _ in family]
    for seed in args.seeds:
        with np.load(os.path.join(args.out, f"drive_{seed}.npz")) as f:
            drive = {k: f[k] for k in f.files}
        starts = rank_dream.starts_of(drive, world, world_model.hidden_dim, args.starts, args.horizon, args.world_steering)
        for i, index in enumerate(drivers):
            real[i].append(real_windows(drive, seed, index, args, world, starts))
        first = world.reward(*(rank_dream.tiled(starts[k], len(family)) for k in ("z", "h_world")))[:, 1]
        shown = []
        steps = rank_dream.dream(driver, world, family, starts, args.horizon, seed, False, args.world_steering,
                                 frames=shown)["off_steps"]
        # The off-road chance of the state each frame shows: the start's, then each step's.
        off = np.concatenate([first.reshape(len(family), args.starts, 1), steps[:, :, :-1]], 2)
        seen = np.stack([np.stack([*sight(frames), across(frames)]) for frames in shown], 2)  # (3, rows, horizon)
        seen = seen.reshape(3, len(family), args.starts, args.horizon)
        for i in range(len(family)):
            dreamt[i].append(np.concatenate([off[i][None], seen[:, i]]))
    report = {}
    for i, d in enumerate(family):
        measured = {"real": np.concatenate(real[i], 1), "dream": np.concatenate(dreamt[i], 1)}
        report[d.name] = {side: figures(m, args.every) for side, m in measured.items()}
        report[d.name]["since_leaving"] = {side: sight_since_leaving(m) for side, m in measured.items()}
        for side in ("real", "dream"):
            cells = "  ".join(f"{b['decisions'][0]}-{b['decisions'][1]}: off {b['off_road']:.2f} sight "
                              f"{b['in_sight']:.2f} ahead {b['ahead']:.2f} sight where off "
                              + ("-" if b["in_sight_where_off"] is None else f"{b['in_sight_where_off']:.2f}")
                              + (f" head {b['head_on_real']:.2f}" if "head_on_real" in b else "")
                              for b in report[d.name][side])
            print(f"{d.name:24} {side:5} {cells}", flush=True)
        for side in ("real", "dream"):
            cells = "  ".join(f"{since_label(*b['since'])}: {share(b['in_sight'])} ({b['frames']})"
                              for b in report[d.name]["since_leaving"][side])
            print(f"{d.name:24} {side:5} road in sight, decisions since leaving (from decision {MEMORY + 1}): {cells}",
                  flush=True)
        report[d.name]["beside"] = {side: road_beside(m) for side, m in measured.items()}
        for side in ("real", "dream"):
            b = report[d.name]["beside"][side]
            cells = "  ".join(f"{place_label(*c['place'])}: {c['decisions']} off {share(c['off_road'])} lost {share(c['lost'])}"
                              for c in b["places"] if c["decisions"])
            print(f"{d.name:24} {side:5} road beside the car (from decision {MEMORY + 1}): gone {share(b['gone'])}, "
                  f"off there {share(b['off_road_where_gone'])}; by place: {cells}", flush=True)
    if args.report:
        with atomic_write(args.report) as f:
            f.write(json.dumps({"seeds": args.seeds, "temperature": args.temperature,
                                "world_steering": list(args.world_steering), "drivers": report}).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

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
range between the best and the worst driver) and the Pearson correlation of the means; each
driver's off-road gap, dreamt less real, with its standard error paired by track, and how many
drivers it puts outside 0.1 by more than two of them; and the dream's road memory: how well the
unchanged driver's steering in the dream follows its real steering from the same starts,
decision by decision (the policy steers by the road it sees, so the correlation falls where the
dream's road stops being the real one), and how it steers on the roads the dream makes up past
that (its mean |steering|, change a decision and shares of bends left and right from decision 11
on, dream and real: the two agree where the made-up roads are as curvy, as steady and as often
bent each way as the real ones).

``--futures N`` (with ``--temperature``) draws N futures from each start: the dream's figures are
their means, and each driver's spread over them is reported beside them, with its correlation over
the family with the dream's error in ranks (does the dream doubt where it is wrong?).
``--off-road-read midmean`` reads a start's off-road share as the mean of the middle half of its
futures' shares, not of them all (and each decision's chance in the table by decision alike).
``--world-steering GAIN,LEAD`` steps the world with each steering s as ``GAIN * s + LEAD * (s - the
decision before's s)``, held at full lock (±1), the drivers' memory with s: a diagnostic of the
world's steering answer.

``--through-frames``: the drivers read the dream's frames through their encoder (150x slower).
``--world FILE`` dreams with another model's transition and heads (the drivers keep the policy of
``--weights`` and step its transition for their own memory): a world model is judged without
changing the drivers. ``--judge`` draws the world's futures through the built-in judge's sampler
(`Model.judge`, learnt for the default's world) with its settings, `JUDGE_STEERING`,
`JUDGE_TEMPERATURE`, `JUDGE_FUTURES` and `JUDGE_OFF_ROAD_READ`, unless ``--world-steering``,
``--temperature``, ``--futures`` or ``--off-road-read`` say otherwise (docs/judging.md).
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
from .family import CHECK, CLIFF, FAMILIES as PROBE_FAMILIES, FAMILY, HOLDS, SMALL, SPEEDS, ChangedAgent, Driver
from . import failures, rank_real
from .rank_dream import OFF_ROAD_READS, dream_futures, open_loop, start_decisions, starts_of
from .rank_figures import bend_sums, leaving, leaving_counts, made_up_roads, print_report, road_memory, summary
from .view import parse_seeds


#: The probe's families, and ``learnt``: the failure data's own drivers (`failures.training_family`),
#: whose drives on other tracks the judge's sampler learnt from: a world checked on new tracks with
#: drivers it saw (docs/history/coming_back.md).
FAMILIES = {**PROBE_FAMILIES, "learnt": failures.training_family()}

# The judge's settings, chosen on the tuning tracks 15600-15619 (docs/history/judge_wheel.md): its
# world steps with each steering GAIN x and a LEAD on its change, held at full lock (the default's
# transition answers the wheel short of the real car: probe-real 0.82-1.06x in 5 steps; the lead
# brings a pulled car back past the view; `world_steering`, chosen with the training family's
# tracks too, with the judge's widened read-out: docs/history/widened.md), at a temperature below 1
# (hotter futures take a car with a steady pull off the road sooner than the real one leaves), and
# its figures are the means of 16 futures (with 4 a driver's dreamt off-road share still moves by
# 0.05 from one draw to another), but for a start's off-road share, the mean of their middle half
# (`rank_dream.OFF_ROAD_READS`: the mean of futures that split flattens the dream's cliff for
# steady pulls; docs/history/midmean.md).
JUDGE_STEERING, JUDGE_TEMPERATURE, JUDGE_FUTURES, JUDGE_OFF_ROAD_READ = (1.8, 0.3), 0.7, 16, "midmean"


def dream_settings(args, own: dict) -> None:
    """Sets each of the dream's settings ``own`` names (``world_steering``, ``temperature``,
    ``futures``, ``off_road_read``) that the command line left unset: the judge's with ``--judge``,
    else ``own``'s."""
    judge = {"world_steering": JUDGE_STEERING, "temperature": JUDGE_TEMPERATURE, "futures": JUDGE_FUTURES,
             "off_road_read": JUDGE_OFF_ROAD_READ}
    for name, value in own.items():
        if getattr(args, name, None) is None:
            setattr(args, name, judge[name] if args.judge else value)


def kept_actions(drive: str) -> bool:
    """Whether the behaviour drive ``drive`` (``drive_SEED.npz``) kept its actions."""
    with np.load(drive) as f:
        return "actions" in f.files


def real_job(job) -> dict:
    """One driver on one track: read from ``--out`` when an earlier run drove it (the behaviour
    drive again where ``--windows`` needs the actions an older run did not keep)."""
    args, index, seed = job
    path = os.path.join(args.out, "real", rank_real.drive_name(args, index, seed))
    drive = os.path.join(args.out, f"drive_{seed}.npz")
    if os.path.exists(path) and not (index == 0 and args.windows and not kept_actions(drive)):
        with open(path) as f:
            return json.load(f)
    agent = ChangedAgent(args.family[index], seed=seed * 1000 + index, model=rank_real.process_model(args.weights))
    figures, states, trace = rank_real.drive_real(agent, seed, args.frames, keep_states=index == 0)
    figures.update(driver=index, seed=seed)
    if index == 0:  # the behaviour drive: the dream's starts are states of it
        z, h, v, steer = (np.stack([s[i] for s in states]).astype(np.float32) for i in range(4))
        with atomic_write(drive) as f:
            np.savez(f, z=z, h=h, speed=v, steer=steer, first=np.int64(agent.warmup), **trace)
    with atomic_write(path) as f:
        f.write(json.dumps(figures).encode())
    return figures


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
               futures=args.futures, off_road_read=args.off_road_read, world_steering=list(args.world_steering),
               value=args.value,
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
                   help="the world steps with GAIN * s + LEAD * (s - the decision before's s) for each steering s, "
                        "held at full lock, ±1 (the drivers' memory steps with s); default 1, with --judge "
                        "JUDGE_STEERING")
    p.add_argument("--family", choices=list(FAMILIES), default="all",
                   help=f"all: the {len(FAMILY)} drivers; small: {len(SMALL)} (tests); holds: the clone and "
                        f"{len(HOLDS) - 1} constant steerings, hands off among them (with --windows --horizon 20); "
                        f"check: {len(CHECK)} other drivers, none of them another family's "
                        "(a second family, for a world tuned on all); cliff: the clone and "
                        f"{len(CLIFF) - 1} steady pulls either side of where it lets go; speeds: the clone and "
                        f"{len(SPEEDS) - 1} target speeds up to {SPEEDS[-1].speed:g}x; learnt: the failure "
                        f"data's {len(FAMILIES['learnt'])} drivers, whose drives the judge learnt from")
    p.add_argument("--horizon", type=int, default=40, help="dream decisions from each start")
    p.add_argument("--starts", type=int, default=7, help="starts per track")
    p.add_argument("--temperature", type=float,
                   help="sampled futures (0: the mean dream, the default; with --judge JUDGE_TEMPERATURE)")
    p.add_argument("--futures", type=int,
                   help="sampled futures from each start (with --temperature): the dream's figures their means, "
                        "and each driver's spread over them reported (default 1; with --judge JUDGE_FUTURES)")
    p.add_argument("--off-road-read", choices=list(OFF_ROAD_READS),
                   help="a start's off-road share from its futures: their mean, or the mean of their middle half "
                        "(default mean; with --judge JUDGE_OFF_ROAD_READ)")
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
    dream_settings(args, {"world_steering": (1.0, 0.0), "temperature": 0.0, "futures": 1, "off_road_read": "mean"})
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

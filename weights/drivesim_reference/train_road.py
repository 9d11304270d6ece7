"""`train.py road`: a world's made-up roads held to the real roads' bends (docs/judging.md, "Roads
that bend like the real ones").

A world that reads CarRacing's view knows about 10 decisions of road ahead; past them its texture
net makes the road up. The judge's made-up roads hardly bend: the unchanged clone steers past
±0.05 in 3 % of its decisions each way there, against 23 % left and 11 % right on the real laps,
so a pulled car that leaves them finds no bend of its own side to come back through. This run
fine-tunes the file's texture net (`transition.texture.*`; every other tensor is kept) so that the
clone, dreamt from the real starts of `python -m drivesim.carracing.rank --family learnt --windows
--out DIR` (DIR is --windows), steers from decision --road-from on as the real clone does from the
same starts along its behaviour drive. Per bin of 10 decisions it compares

    the batch's mean steering and mean |steering| (in units of 0.05), and
    the soft shares of steering past -e and +e for each e of --edges (sigmoids of softness
    --softness, in units of 0.1, weight --shares),

with the real clone's. The gradient reaches the texture net through the clone reading the dreamt
codes. The rest of the rank's `learnt` family (the failure data's drivers, none of the probe's)
drives the same starts in the same batch, for two things: --anchor times the squared difference of
the draws from the starting texture net's on every row keeps what the road term does not ask for
as it was; and their off-road chances (the reward head's) against their real shares in the windows
are the run's **fit**, the mean absolute gap over the family (each chance the mean of FIT_DRAWS
dreams), which does not train.

What one seed makes is a draw: of four seeds of the same recipe one had 16 of 17 drivers within
0.1 of the real share on the tuning tracks and the others 9 to 11, and their fits ranked them as
the tuning tracks did (docs/history/road_seeds.md). So --seeds trains each seed in turn and writes
the one with the smallest fit (each seed's run starts at `torch.manual_seed(seed)` before the world
is read, so it is the same alone or among others). The file written is the whole world; `python -m
drivesim sampler OUT --world W --out FILE` writes its sampler file. The dream is the rank's at its
settings (--temperature, the world's steering shaped by --world-steering and held at full lock, the
drivers' own memory stepped on the codes they see), in torch.
Adam (--lr), the gradient's norm clipped to 1, every start in each step unless --batch says fewer.
With --checkpoint FILE the run writes its state every --checkpoint-every steps (atomically) and a
run started again with the same arguments goes on from there to the same bytes.
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
import zipfile

import numpy as np
import torch
from safetensors import safe_open

from drivesim import _files
from drivesim.carracing import failures
from drivesim.carracing.control import SPEED_MAX
from drivesim.carracing.rank import JUDGE_STEERING, shaping
from drivesim.carracing.rank_dream import steering_shaped, window_starts
from drivesim_reference.model import load_drivesim
from drivesim_reference.train_driver import speed_after
from drivesim_reference.train_heads import Source, action_ranges

CHECKPOINT_FORMAT = "drivesim train.py road checkpoint 1"
HORIZON, STARTS = 40, 7  # `rank --windows`' windows: HORIZON decisions from STARTS starts a track
BIN = 10  # decisions a bin of the road term compares
STEERING_UNIT, SHARE_UNIT = 0.05, 0.1  # the road term's units of steering and of shares
# The fit's dreams of every start: one moves it by about 0.01, as much as some seeds differ.
FIT_DRAWS = 4
FAMILY = "learnt"  # the rank's family whose windows the run reads (`failures.training_family`)


def load_windows(model, cfg, folder: str, shaping: tuple) -> dict:
    """The starts of every track of ``folder`` (a `rank --family learnt --windows --out`): codes,
    the clone's memory, the world's hidden state (its transition stepped along the drive with the
    steering shaped by ``shaping``, `rank_dream.steering_shaped`), speeds, the steering before each
    start, the clone's real steering over the HORIZON decisions from each (NaN past a drive's end)
    and every driver's real off-road flags (drivers, starts, HORIZON). A track without every
    driver's windows is left out; a file that cannot be read is a ValueError."""
    n = len(failures.training_family())
    seeds = sorted(int(f[6:-4]) for f in os.listdir(folder) if f.startswith("drive_") and f.endswith(".npz")
                   and f[6:-4].isdigit()) if os.path.isdir(folder) else []
    parts = []
    for seed in seeds:
        files = [os.path.join(folder, f"windows_{HORIZON}x{STARTS}", f"{FAMILY}_{i}_{seed}.json") for i in range(n)]
        if all(os.path.exists(f) for f in files):
            try:
                parts.append(track(model, cfg, os.path.join(folder, f"drive_{seed}.npz"), files, shaping))
            except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile) as e:
                raise ValueError(f"--windows {folder}: track {seed}: {e}") from e
    if not parts:
        raise ValueError(f"--windows {folder}: no track with the windows of every driver of the `{FAMILY}` family "
                         f"(run `python -m drivesim.carracing.rank --family {FAMILY} --windows --out {folder}`)")
    z, memory, hidden, speed, previous, steer, off = zip(*parts)
    return dict(z=torch.cat(z), memory=torch.cat(memory), hidden=torch.cat(hidden), speed=torch.cat(speed),
                previous=torch.cat(previous), steer=torch.cat(steer), off=torch.cat(off, 1), tracks=len(parts))


def track(model, cfg, drive_file: str, files: list, shaping: tuple) -> tuple:
    """One track's part of `load_windows`: its behaviour drive ``drive_file`` and the drivers' windows ``files``."""
    with np.load(drive_file) as f:
        drive = {k: f[k] for k in ("z", "h", "speed", "steer", "first")}
    if drive["z"].shape[1:] != (cfg.z_dim,) or drive["h"].shape[1:] != (cfg.hidden_dim,):
        raise ValueError("its codes and memories are another model's shape")
    if not all(np.isfinite(drive[k]).all() for k in ("z", "h", "speed", "steer")):
        raise ValueError("its drive holds numbers that are not finite")
    _, at = window_starts(drive, STARTS, HORIZON)
    h = torch.zeros(1, cfg.hidden_dim)
    along = []
    with torch.no_grad():
        for t in range(max(at) + 1):
            along.append(h[0])
            steer = steering_shaped(drive["steer"][t], drive["steer"][max(t - 1, 0)], shaping)
            c = torch.tensor([[drive["speed"][t], steer]], dtype=torch.float32)
            _, h = model.transition(torch.from_numpy(drive["z"][t:t + 1]).float(), h, c)
    real = np.full((len(at), HORIZON), np.nan, np.float32)
    for j, t in enumerate(at):
        real[j, :len(drive["steer"][t:t + HORIZON])] = drive["steer"][t:t + HORIZON]
    flags = []
    for path in files:
        with open(path) as f:
            rows = json.load(f)["off"]
        if len(rows) != len(at) or any(len(r) > HORIZON or not set(r) <= {0, 1} for r in rows):
            raise ValueError(f"{path}: not {len(at)} windows (its drive's starts) of at most {HORIZON} flags 0 or 1")
        flags.append([r + [math.nan] * (HORIZON - len(r)) for r in rows])
    return (torch.from_numpy(drive["z"][at]).float(), torch.from_numpy(drive["h"][at]).float(),
            torch.stack([along[t] for t in at]), torch.from_numpy(drive["speed"][at]).float(),
            torch.tensor([drive["steer"][max(t - 1, 0)] for t in at], dtype=torch.float32),
            torch.from_numpy(real), torch.tensor(flags, dtype=torch.float32))


class RoadRun:
    """One seed's run: the texture net learning, its starting copy and Adam."""

    def __init__(self, model, cfg, data, args, ranges):
        self.model, self.data, self.args, self.ranges = model, data, args, ranges
        self.start = copy.deepcopy(model.transition.texture)
        for q in model.transition.texture.parameters():
            q.requires_grad_(True)
        self.opt = torch.optim.Adam(model.transition.texture.parameters(), lr=args.lr)
        family = failures.training_family()
        self.params = {k: torch.tensor([float(getattr(d, k)) for d in family]) for k in
                       ("gain", "bias", "speed", "noise", "delay")}
        self.drivers = len(family)

    def modules(self):
        return dict(texture=self.model.transition.texture, opt=self.opt)

    def dream(self, rows):
        """Every driver from the starts ``rows``: the off-road chances (drivers, len(rows), HORIZON),
        the anchor, and the clone's steering (len(rows), HORIZON) read with a gradient."""
        a, d, n, k = self.args, self.data, self.drivers, len(rows)
        tr, tex, policy, reward = self.model.transition, self.model.transition.texture, self.model.policy, \
            self.model.reward
        z, h_d, h_w = (d[key][rows].repeat(n, 1) for key in ("z", "memory", "hidden"))
        v, previous = d["speed"][rows].repeat(n), d["previous"][rows].repeat(n)
        row = torch.arange(n).repeat_interleave(k)
        g, b, sp, nz, dl = (self.params[key][row] for key in ("gain", "bias", "speed", "noise", "delay"))
        dl = dl.long()
        queue, chances, anchor, road = None, [], [], []
        low, high = self.ranges
        for _ in range(HORIZON):
            seen = z.detach()  # the drivers read the dream; only the clone's rows below carry a gradient
            out = policy(seen, h_d)
            road.append(policy(z[:k], h_d[:k])[:, 1].clamp(-1.0, 1.0))
            steer = (g * out[:, 1].clamp(-1.0, 1.0) + b + nz * torch.randn(len(z))).clamp(-1.0, 1.0)
            target = (sp * out[:, 0].clamp(float(low[0]), float(high[0]))).clamp(0.0, SPEED_MAX)
            decided = torch.stack([target, steer], 1).detach()
            if queue is None:  # a window starts with its first decision already in the past
                queue = [decided] * (int(dl.max()) + 1)
            queue = queue[1:] + [decided]
            applied = torch.stack(queue)[len(queue) - 1 - dl, torch.arange(len(z))]
            action = torch.stack([v, applied[:, 1]], 1)
            with torch.no_grad():
                _, h_d = tr(seen, h_d, action)
            mean, h_w = tr(z, h_w, torch.stack([v, steering_shaped(applied[:, 1], previous, a.world_steering)], 1))
            previous = applied[:, 1]
            eps = a.temperature * torch.randn_like(mean)
            drawn = tex(eps, h_w)
            with torch.no_grad():
                drawn0 = self.start(eps, h_w)
            anchor.append((drawn - drawn0).square().mean())
            z = mean + drawn
            v = speed_after(v, applied[:, 0])
            chances.append(reward(z, h_w)[:, 1])
        return torch.stack(chances, 1).reshape(n, k, HORIZON), torch.stack(anchor).mean(), torch.stack(road, 1)

    def road_term(self, dreamt, real):
        """The dreamt clone's steering against the real one's (module docstring), from --road-from on."""
        a = self.args
        seen = ~torch.isnan(real)
        real = torch.nan_to_num(real)
        sides = [(lambda x, e=e: torch.sigmoid((-e - x) / a.softness)) for e in a.edges] + \
                [(lambda x, e=e: torch.sigmoid((x - e) / a.softness)) for e in a.edges]
        terms = []
        for k0 in range(a.road_from, HORIZON, BIN):
            mask = seen[:, k0:k0 + BIN].float()
            count = mask.sum().clamp(min=1)

            def gap(f, unit):
                return (((f(dreamt[:, k0:k0 + BIN]) * mask).sum() - (f(real[:, k0:k0 + BIN]) * mask).sum())
                        / count / unit).square()
            terms += [gap(lambda x: x, STEERING_UNIT), gap(torch.abs, STEERING_UNIT)]
            if a.shares:
                terms += [a.shares * gap(f, SHARE_UNIT) for f in sides]
        return torch.stack(terms).mean()

    def step(self, rows) -> dict:
        _, anchor, road = self.dream(rows)
        term = self.road_term(road, self.data["steer"][rows])
        self.opt.zero_grad()
        (term + self.args.anchor * anchor).backward()
        torch.nn.utils.clip_grad_norm_(self.model.transition.texture.parameters(), 1.0)
        self.opt.step()
        return dict(road=float(term.detach()), anchor=float(anchor.detach()))

    @torch.no_grad()
    def fit(self, draws: int = FIT_DRAWS) -> tuple[float, list]:
        """The fit (module docstring) over every start, the dream drawn ``draws`` times, and each
        driver's (dream, real) share."""
        every = torch.arange(len(self.data["z"]))
        chances = torch.stack([self.dream(every)[0].clamp(0, 1) for _ in range(draws)]).mean(0)
        shares = [(float(chances[i].mean()), float(self.data["off"][i].nanmean())) for i in range(self.drivers)]
        return float(np.mean([abs(d - r) for d, r in shares])), shares


def save_state(path, state: dict):
    """The run's state to ``path``, atomically (the torch and Adam states, the best seed so far)."""
    with _files.atomic_write(path) as f:
        torch.save(state, f)


def restore_state(path, arguments: dict) -> dict | None:
    """The state a run with ``arguments`` wrote to ``path`` (None where there is none)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        return None
    except Exception as e:  # torch.load raises many kinds for a file that is not a checkpoint
        raise ValueError(f"{path}: not a checkpoint to resume from: {e}") from e
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT or state.get("arguments") != arguments:
        raise ValueError(f"{path}: a checkpoint of another run (other arguments): remove it or name another file")
    return state


def with_sampler(model, cfg, weights: str, sampler: str):
    """The model with the texture net of the sampler file ``sampler`` (`python -m drivesim
    sampler`), which the crate checks was learnt for this world, and its read-out where it
    carries one (`python -m drivesim widen`)."""
    import drivesim
    from drivesim_reference.model import Texture

    try:
        drivesim.Model.load(weights, sampler=sampler)
    except Exception as e:  # the crate's typed errors: not a sampler, another world's
        raise ValueError(f"--sampler {sampler}: {e}") from e
    prefix = "transition.texture."
    with safe_open(sampler, "pt") as f:
        tensors = {k[len(prefix):]: f.get_tensor(k).float() for k in f.keys() if k.startswith(prefix)}
        with torch.no_grad():
            for name in ("A", "a"):  # the crate took both or neither
                if f"transition.{name}" in f.keys():
                    getattr(model.transition, name).copy_(f.get_tensor(f"transition.{name}").float())
    own = getattr(model.transition, "texture", None)
    if own is None or own.hidden.out_features != tensors["hidden.weight"].shape[0]:
        model.transition.texture = Texture(cfg, tensors["hidden.weight"].shape[0])
    model.transition.texture.load_state_dict(tensors)
    return model


def world(args):
    """The world to fine-tune (with --sampler's texture net), its parameters frozen, and its config."""
    model, cfg = load_drivesim(args.weights)
    if args.sampler:
        model = with_sampler(model, cfg, args.weights, args.sampler)
    heads = model.heads()
    if getattr(model.transition, "texture", None) is None or "policy" not in heads or "reward" not in heads:
        raise ValueError(f"{args.weights}: the run needs a texture net (or --sampler), the policy and the reward head")
    for p in model.parameters():
        p.requires_grad_(False)
    return model, cfg


def road(args):
    check(args)
    model, cfg = world(args)
    with safe_open(args.weights, "pt") as f:
        ranges = action_ranges(f.metadata() or {})
    if ranges is None:
        raise ValueError(f"{args.weights}: no `drivesim.actions` metadata (the policy's speed range)")
    source = Source(args.weights, args.out)
    data = load_windows(model, cfg, args.windows, args.world_steering)
    starts = len(data["z"])
    batch = min(args.batch or starts, starts)
    print(f"{data['tracks']} tracks, {starts} starts, {len(data['off'])} drivers; seeds {args.seeds}, "
          f"{args.steps} steps of {batch} starts", flush=True)
    arguments = {k: str(v) for k, v in sorted(vars(args).items())
                 if k not in {"out", "checkpoint", "checkpoint_every", "mode", "log_every"}}
    state = (restore_state(args.checkpoint, arguments) if args.checkpoint else None) or \
        dict(format=CHECKPOINT_FORMAT, arguments=arguments, best=None, done=[], current=None)
    for seed in args.seeds:
        if seed in state["done"]:
            continue
        torch.manual_seed(seed)  # before the world is read: a seed's run is the same alone or among others
        model, cfg = world(args)
        run = RoadRun(model, cfg, data, args, ranges)
        current = state["current"]
        first = 0
        if current and current["seed"] == seed:  # resumed where the checkpoint was written
            for k, m in run.modules().items():
                m.load_state_dict(current["modules"][k])
            torch.set_rng_state(current["random"])
            first = current["step"]
        else:
            # One draw only: a glance at where the seed starts (the seeds' runs draw on from here).
            print(f"seed {seed}: the starting texture net's fit {run.fit(draws=1)[0]:.6f} (one draw)", flush=True)
        sums, clock = {}, time.time()
        for step in range(first, args.steps):
            rows = torch.randperm(starts)[:batch]
            for k, v in run.step(rows).items():
                sums[k] = sums.get(k, 0.0) + v
            if (step + 1) % args.log_every == 0:
                shown = ", ".join(f"{k} {v / args.log_every:.4f}" for k, v in sums.items())
                print(f"seed {seed}, step {step + 1}/{args.steps}: {shown} ({time.time() - clock:.0f} s)", flush=True)
                sums = {}
            if args.checkpoint and (step + 1) % args.checkpoint_every == 0 and step + 1 < args.steps:
                state["current"] = dict(seed=seed, step=step + 1, random=torch.get_rng_state(),
                                        modules={k: m.state_dict() for k, m in run.modules().items()})
                save_state(args.checkpoint, state)
        fit, shares = run.fit()
        print(f"seed {seed}: fit {fit:.6f} (off the road, dream / real: " + ", ".join(
            f"{d.name} {s[0]:.2f}/{s[1]:.2f}" for d, s in zip(failures.training_family(), shares)) + ")", flush=True)
        if state["best"] is None or fit < state["best"]["fit"]:
            state["best"] = dict(fit=fit, seed=seed, texture=copy.deepcopy(model.transition.texture.state_dict()))
        state["done"], state["current"] = state["done"] + [seed], None
        if args.checkpoint:
            save_state(args.checkpoint, state)
    best = state["best"]
    model.transition.texture.load_state_dict(best["texture"])
    print(f"kept seed {best['seed']} (fit {best['fit']:.6f})", flush=True)
    source.write(model, cfg, args.out)


def seed_list(text: str) -> list:
    """``--seeds``' ``0,1,2`` or ``0-3``."""
    try:
        if "-" in text:
            lo, hi = (int(v) for v in text.split("-"))
            seeds = list(range(lo, hi + 1))
        else:
            seeds = [int(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--seeds {text!r}: not N,N,... or LO-HI") from None
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"--seeds {text!r}: want distinct seeds from 0")
    return seeds


def edges(text: str) -> list:
    try:
        out = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--edges {text!r}: not numbers separated by commas") from None
    if not all(0.0 < e < 1.0 for e in out):
        raise ValueError(f"--edges {text!r}: each from 0 to 1, not either")
    return out


def check(args):
    args.seeds, args.edges = seed_list(args.seeds), edges(args.edges)
    numbers = dict(lr=args.lr, anchor=args.anchor, shares=args.shares, softness=args.softness,
                   temperature=args.temperature)  # --world-steering is checked as it is read (`rank.shaping`)
    if not all(math.isfinite(v) for v in numbers.values()) or args.lr <= 0 or args.softness <= 0 \
            or min(args.anchor, args.shares, args.temperature) < 0:
        raise ValueError(f"--lr and --softness must be above 0, --anchor, --shares and --temperature at "
                         f"least 0, all finite: {numbers}")
    if args.steps < 0 or args.batch < 0 or not 0 <= args.road_from < HORIZON or args.log_every < 1 \
            or args.checkpoint_every < 1:
        raise ValueError(f"--steps and --batch must be at least 0, --road-from from 0 to {HORIZON - 1}, "
                         "--log-every and --checkpoint-every at least 1")


def add_arguments(t):
    """`train.py road`'s arguments."""
    t.add_argument("--weights", required=True, help="the world whose texture net is fine-tuned (the other tensors "
                   "are kept)")
    t.add_argument("--sampler", help="start from this sampler file's texture net instead (`python -m drivesim "
                   "sampler`), e.g. weights/judge.safetensors")
    t.add_argument("--windows", required=True, help="`python -m drivesim.carracing.rank --family learnt --windows "
                   "--out DIR`'s DIR: the real drives and windows of the training family's tracks")
    t.add_argument("--out", required=True, help="where to write the world with the kept seed's texture net")
    t.add_argument("--seeds", default="0", help="seeds to train, each in turn (N,N,... or LO-HI); the one with "
                   "the smallest fit is written")
    t.add_argument("--steps", type=int, default=300)
    t.add_argument("--batch", type=int, default=0, help="starts a step (0: all)")
    t.add_argument("--lr", type=float, default=1e-4)
    t.add_argument("--anchor", type=float, default=3.0, help="weight of the draws' squared difference from the "
                   "starting texture net's")
    t.add_argument("--road-from", type=int, default=10, help="the road term's first decision (10: past the view)")
    t.add_argument("--edges", default="0.05,0.1", help="the shares' edges, each both ways")
    t.add_argument("--shares", type=float, default=1.0, help="weight of the shares' terms")
    t.add_argument("--softness", type=float, default=0.02, help="the shares' sigmoids' softness")
    t.add_argument("--temperature", type=float, default=0.7, help="the draws' temperature (the judge's)")
    t.add_argument("--world-steering", type=shaping, default=JUDGE_STEERING, metavar="GAIN[,LEAD]",
                   help="the world's steering shaped as `rank --world-steering` shapes it (default the judge's)")
    t.add_argument("--log-every", type=int, default=50)
    t.add_argument("--checkpoint", help="checkpoint file, written every --checkpoint-every steps and read back")
    t.add_argument("--checkpoint-every", type=int, default=50)

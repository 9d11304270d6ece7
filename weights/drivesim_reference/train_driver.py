"""`train.py driver`: a driver learnt inside the dream by the gradient of the dream's own return
(issue 60, docs/learning.md). It never sees an expert's label or a real reward: the world model's
reward head, its off-road chance and its value head are the only signal.

The driver is a head of the policy's shape (model.py `Policy`: one tanh layer on `[z | h]`, then
the speed to drive at and the steering), started at random with its output layer at zero (a
straight drive at --first-speed). Each step draws --batch real states (every decision of the
episodes past their first SETTLE, the code of the frame seen there and the transition's hidden
state stepped along the episode with the recorded actions, from zeros; on the road only with
--on-road-starts) and rolls the driver --horizon decisions in the dream:

    action = (speed now, clamp(steering, -1, 1))
    h' = tanh(W h + V z + U (speed now, gain * steering) + b)   (gain: 1, or drawn per drive
                                                                  from --steer-gain LO,HI)
    z' = A h' + a + texture(temperature * noise, h')       (the crate's sampled future)
    speed' = speed_after(speed, clamp(target, 2, --top-speed))   (drivesim.carracing.control; with
             --brake-gradient its dead band passes a gradient back)
    return = sum_t discount^t (reward(z', h') - --off-road-cost * off_road(z', h')
                               - --lateral-cost * max(0, (speed / 50)^2 |steering| - --lateral-limit))
             (discount: the value head's, 1 in a world without one)
             [+ discount^H value(z_H, h_H) with --value]

and Adam (lr --lr, the gradient's norm clipped to 100) follows the gradient of the mean return,
which runs through the sampled futures (the noise is drawn, the texture net's offset kept in the
graph), the transition and the speed's response back to every decision. Outputs past the
ranges clamped here (steering past +-1, a target outside 2..--top-speed) pay a squared penalty,
which keeps them near: the crate clips the steering to +-1 but the target only to the file's
speed range (docs/learning.md's driver, --top-speed 40, gives at most 41.1 on its starts).

--steer-gain LO,HI is a guard of dynamics randomisation: every drive's steering reaches the
transition scaled by its own gain, drawn uniformly from LO..HI, so that the driver learns to
drive dreams whose steering answers more than the world's does (the worlds before 2026-12-02 moved
the road 0.45-0.8x as far as the real car's; the default's since answers about as far, and a
driver learnt in it needs no gain: docs/judging.md, docs/learning.md). The driver still gives, and
the real car still gets, the steering itself.

--lateral-cost C is a guard of what the recordings say and the dream does not: a car steered
hard at speed leaves the road. Of the failure drives' decisions on the road (tracks
12000-12031), 11 % leave it within 8 decisions where the lateral load (speed / 50)^2 |steering|
is under 0.2, and 19, 27, 30, 34 and 41 % at 0.2-0.3, 0.3-0.4, 0.4-0.5, 0.5-0.7 and above
(docs/learning.md); each decision pays C per unit of load above --lateral-limit (0.2). With
--lateral-by speed the cost's gradient reaches the steering only through the states it leads to
(its own size held as given), so that the driver pays for a bend by slowing for it, not by
steering less than the road needs.

With --checkpoint FILE the run writes the driver, Adam's state and the random state every
--checkpoint-every steps (atomically); a run started again with the same arguments goes on from
there to the same bytes (on the same device). The written file is the input with `policy.*`
replaced by the learnt driver and the clone's `pace.*` head left out (a driver learnt in the dream
drives at its own speed): `make_agent("dreamt", weights=OUT)` drives it.

--look DRIVER trains nothing: it rolls DRIVER's policy (a file this command wrote) in the world's
dream, --batch drives of --horizon decisions from the starts drawn with --seed, and prints what it
does there as JSON: the return and off-road chance, its speed (all decisions, and where it steers
0.2 or more), how often it steers so, asks for --top-speed (within 2 units/s) or brakes, and its
lateral load over --lateral-limit. A look at a driver before any real drive (docs/learning.md).
--look A,B,... looks at each from the same starts and the same noise, a line each, and then names
the one of least lateral load: of four drivers learnt by one recipe with four new seeds, that load
predicted the order of their real scores, where the dream's return did not (docs/learning.md,
"Eight seeds").

--average A,B,... trains nothing either: it writes the world of --weights with the mean of these
drivers as its policy, one head as wide as theirs together (their hidden layers stacked, their
output layers side by side over their number, their output biases averaged), so that the crate
drives their mean action exactly as it drives one driver. Each must be a driver this command
learnt afresh in that same world (every other network equal); their widths together at most
hidden_dim. The recipe's seeds differ by as much as a hundred tracks do; the mean of four drove
+17.9 ± 6.9 over its members' average on 100 tracks, and below the best of them (docs/learning.md).

--from-policy starts the driver as the file's policy instead (the clone fine-tuned in the dream;
`pace.*` kept, `make_agent("cloned", weights=OUT)` drives it), and --stay C pays C per squared
change of its outputs from the file's policy (target / --top-speed, steering) at every decision.
"""

from __future__ import annotations

import copy
import json
import math
import time

import torch
from torch import nn

from drivesim_reference.model import Policy, load_drivesim
from drivesim_reference.train_heads import Source, encode_view, load_episodes
from drivesim_reference.train_texture import restore, save_checkpoint

CHECKPOINT_FORMAT = "drivesim train.py driver checkpoint 1"
# Decisions of an episode before a start is drawn (drivesim.carracing.dream_train's SETTLE).
SETTLE = 12
# The speed control's response per decision (drivesim.carracing.control: GAIN, ACCELERATION,
# BRAKE_DEAD) and the lowest target speed a driver may give.
GAIN, ACCELERATION, BRAKE_DEAD, LOWEST = 0.2, 2.0, 4.0, 2.0
# The penalty's weight on outputs the crate would clip.
CLIP_PENALTY = 1.0


def speed_after(speed: torch.Tensor, target: torch.Tensor, brake_gradient: bool = False) -> torch.Tensor:
    """control.speed_after in torch: up by GAIN of the gap (at most ACCELERATION), down at once
    where the target is more than BRAKE_DEAD below. The dead band between passes no gradient: a
    driver at speed that asks for a little less learns nothing of braking. With
    `brake_gradient` it passes GAIN's, straight through (the speed itself unchanged)."""
    gap = target - speed
    up = torch.minimum(GAIN * gap, torch.full_like(gap, ACCELERATION))
    dead = torch.zeros_like(gap) if not brake_gradient else GAIN * (gap - gap.detach())
    return speed + torch.where(gap >= 0, up, torch.where(gap < -BRAKE_DEAD, gap, dead))


def real_states(model, data, on_road_only: bool) -> dict:
    """Every decision of `data` past its episode's first SETTLE (on the road only where asked and
    the file records it): the code, the hidden state before the decision and the recorded speed."""
    codes, actions = encode_view(model, data, mirrored=False)
    on_road = data.rewards["on_road"] if data.rewards is not None else None
    z, h, speed = [], [], []
    tr = model.transition
    for start, end in data.bounds():
        hidden = codes.new_zeros(tr.W.shape[0])
        for t in range(start, end):
            if t - start >= SETTLE and (not on_road_only or on_road is None or on_road[t]):
                z.append(codes[t])
                h.append(hidden)
                speed.append(actions[t, 0])
            _, hidden = tr(codes[t], hidden, actions[t])
    if not z:
        raise ValueError(f"no decision past an episode's first {SETTLE}" + (" on the road" if on_road_only else ""))
    return dict(z=torch.stack(z), h=torch.stack(h), speed=torch.stack(speed).float())


class DreamDriver:
    """The driver, its optimiser and the dream it is rolled in (the model's frozen networks)."""

    def __init__(self, model, cfg, args, driver=None):
        self.model, self.args = model, args
        # --from-policy: the file's policy, kept frozen as the anchor of --stay, starts the driver.
        self.anchor = model.policy if args.from_policy else None
        if driver is not None:  # a driver to look at (--look), not to train
            self.driver = driver
        elif self.anchor is not None:
            self.driver = copy.deepcopy(self.anchor).requires_grad_(True)
        else:
            self.driver = Policy(cfg, args.width)
            nn.init.zeros_(self.driver.output.weight)
            with torch.no_grad():
                self.driver.output.bias.copy_(torch.tensor([args.first_speed, 0.0]))
        self.opt = torch.optim.Adam(self.driver.parameters(), lr=args.lr)

    def modules(self):
        return dict(driver=self.driver, opt=self.opt)

    def rollout(self, z, h, speed, noise=None, trace=None) -> tuple[torch.Tensor, ...]:
        """(return, mean off-road chance, clip penalty, move from the file's policy: the last two a
        decision's mean, the move 0 without --from-policy) of each drive from the states `z`, `h`,
        `speed`; `noise` [horizon, N, z] the standard normal draws (None: drawn here); `trace`, a
        list, gets each decision's (speed, steering, the driver's target, lateral load)."""
        a, m = self.args, self.model
        total, off, over, moved = (speed.new_zeros(len(speed)) for _ in range(4))
        # The value head's discount; a world without one sums its rewards as dream-train does.
        weight, discount = 1.0, m.discount if m.discount is not None else 1.0
        low, high = a.steer_gain
        gain = speed.new_empty(len(speed)).uniform_(low, high) if (low, high) != (1.0, 1.0) else 1.0
        for t in range(a.horizon):
            out = self.driver(z, h)
            target, steer = out[:, 0].clamp(LOWEST, a.top_speed), out[:, 1].clamp(-1.0, 1.0)
            over = over + (torch.relu(out[:, 0] - a.top_speed) / a.top_speed).square() \
                + (torch.relu(LOWEST - out[:, 0]) / a.top_speed).square() + torch.relu(out[:, 1].abs() - 1).square()
            if self.anchor is not None:
                start = self.anchor(z, h)
                moved = moved + ((out[:, 0] - start[:, 0]) / a.top_speed).square() + (out[:, 1] - start[:, 1]).square()
            turn = steer.abs().detach() if a.lateral_by == "speed" else steer.abs()
            lateral = torch.relu((speed / 50.0).square() * turn - a.lateral_limit)
            if trace is not None:
                trace.append((speed, steer, out[:, 0], lateral))
            mean, h = m.transition(z, h, torch.stack([speed, gain * steer], 1))
            if a.temperature > 0:
                draw = torch.randn_like(mean) if noise is None else noise[t]
                z = mean + m.transition.texture(a.temperature * draw, h)
            else:
                z = mean
            speed = speed_after(speed, target, a.brake_gradient)
            reward = m.reward(z, h)
            off_road = reward[:, 1].clamp(0.0, 1.0)
            total = total + weight * (reward[:, 0] - a.off_road_cost * off_road - a.lateral_cost * lateral)
            off = off + off_road
            weight *= discount
        if a.value:
            total = total + weight * m.value(z, h)[:, 0]
        return total, off / a.horizon, over / a.horizon, moved / a.horizon

    def step(self, z, h, speed) -> dict:
        total, off, over, moved = self.rollout(z, h, speed)
        loss = -total.mean() + CLIP_PENALTY * over.mean()
        if self.anchor is not None:
            loss = loss + self.args.stay * moved.mean()
        self.opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.driver.parameters(), 100.0)
        self.opt.step()
        return dict(dream_return=float(total.detach().mean()), off_road=float(off.detach().mean()))


def check(args, model, cfg):
    if args.steps < 0 or not 1 <= args.batch <= 65536 or args.horizon < 1 \
            or (args.look is None and not 1 <= args.width <= cfg.hidden_dim):  # a look's driver has its own
        raise ValueError(f"--steps must be at least 0, --batch from 1 to 65536, --horizon at least 1 and --width "
                         f"from 1 to the model's hidden_dim ({cfg.hidden_dim})")
    numbers = dict(lr=args.lr, temperature=args.temperature, off_road_cost=args.off_road_cost,
                   lateral_cost=args.lateral_cost, lateral_limit=args.lateral_limit,
                   top_speed=args.top_speed, first_speed=args.first_speed)
    if not all(math.isfinite(v) for v in numbers.values()) or args.lr <= 0 or args.temperature < 0 \
            or min(args.off_road_cost, args.lateral_cost, args.lateral_limit) < 0 or not LOWEST < args.top_speed \
            or not LOWEST <= args.first_speed <= args.top_speed:
        raise ValueError(f"--lr must be above 0, --temperature, the costs and --lateral-limit at least 0, "
                         f"--top-speed above {LOWEST} and --first-speed from {LOWEST} to it, all finite; got {numbers}")
    low, high = args.steer_gain
    if not (math.isfinite(low) and math.isfinite(high) and 0.0 < low <= high <= 5.0):
        raise ValueError(f"--steer-gain must be LO,HI with 0 < LO <= HI <= 5; got {low},{high}")
    if args.from_policy and "policy" not in model.heads():
        raise ValueError(f"{args.weights}: --from-policy needs a weight file with a policy")
    if not math.isfinite(args.stay) or args.stay < 0 or (args.stay > 0 and not args.from_policy):
        raise ValueError("--stay must be finite, at least 0, and given with --from-policy")
    if args.checkpoint_every < 1:
        raise ValueError("--checkpoint-every must be at least 1")
    heads = model.heads()
    missing = [name for name, there in (("reward head", "reward" in heads),
                                        ("value head (--value)", "value" in heads or not args.value),
                                        ("texture net (--temperature above 0)",
                                         hasattr(model.transition, "texture") or args.temperature == 0))
               if not there]
    if missing:
        raise ValueError(f"{args.weights}: the world model lacks its {', '.join(missing)}")


def look(args, model, cfg, states, path) -> dict:
    """--look: what the driver of `path` does in the world's dream (the module's docstring)."""
    looked, _ = load_drivesim(path)
    policy = looked.heads().get("policy")
    if policy is None or policy.hidden.weight.shape[1] != cfg.z_dim + cfg.hidden_dim:
        raise ValueError(f"--look {path}: a weight file whose policy reads this world's [z, h] "
                         f"({cfg.z_dim} + {cfg.hidden_dim} numbers)")
    torch.manual_seed(args.seed)
    i = torch.randint(len(states["speed"]), (args.batch,))
    trace = []
    with torch.no_grad():
        total, off, _, _ = DreamDriver(model, cfg, args, driver=policy).rollout(
            states["z"][i], states["h"][i], states["speed"][i], trace=trace)
    speed, steer, target, lateral = (torch.stack(x) for x in zip(*trace))
    steers = steer.abs() >= 0.2
    figures = dict(dream_return=total.mean(), off_road=off.mean(), speed=speed.mean(),
                   speed_where_steering=speed[steers].mean() if steers.any() else None,  # null: it never steers so
                   steering=steers.float().mean(), at_top_speed=(target >= args.top_speed - 2.0).float().mean(),
                   braking=(target < speed - BRAKE_DEAD).float().mean(), lateral_excess=lateral.mean())
    return {"driver": str(path), **{k: None if v is None else round(float(v), 4) for k, v in figures.items()}}


def average(args, model, cfg) -> Policy:
    """--average: the drivers' mean as one head (the module's docstring)."""
    world = {k: v for k, v in model.state_dict().items() if not k.startswith(("policy.", "pace."))}
    heads = []
    for path in args.average:
        other, _ = load_drivesim(path)
        theirs = {k: v for k, v in other.state_dict().items() if not k.startswith("policy.")}
        if "policy" not in other.heads() or theirs.keys() != world.keys() \
                or not all(torch.equal(theirs[k], world[k]) for k in world):
            raise ValueError(f"--average {path}: not a driver learnt afresh in the world of {args.weights} (its "
                             "other networks differ, it has no policy, or it keeps the clone's pace head)")
        heads.append(other.policy)
    width = sum(head.width for head in heads)
    if len(heads) < 2 or width > cfg.hidden_dim:
        raise ValueError(f"--average needs two drivers or more, {width} units together at most the model's "
                         f"hidden_dim ({cfg.hidden_dim})")
    mean = Policy(cfg, width)
    with torch.no_grad():
        mean.hidden.weight.copy_(torch.cat([head.hidden.weight for head in heads]))
        mean.hidden.bias.copy_(torch.cat([head.hidden.bias for head in heads]))
        mean.output.weight.copy_(torch.cat([head.output.weight for head in heads], dim=1) / len(heads))
        mean.output.bias.copy_(torch.stack([head.output.bias for head in heads]).mean(0))
    return mean


def driver(args):
    if args.look is None and args.out is None:
        raise ValueError("--out is needed (unless --look)")
    if (args.episodes is None) == (args.average is None) or (args.look and args.average):
        raise ValueError("give --episodes to train or look, or --average to write drivers' mean (not both)")
    model, cfg = load_drivesim(args.weights)
    if args.average is not None:
        model.policy, model.pace = average(args, model, cfg), None
        Source(args.weights, args.out).write(model, cfg, args.out)
        return
    check(args, model, cfg)
    data = load_episodes(args.episodes, cfg, "episodes", rewards=False)
    for p in model.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        states = real_states(model, data, args.on_road_starts)
    if args.look is not None:
        seen = [look(args, model, cfg, states, path) for path in args.look]
        for figures in seen:
            print(json.dumps(figures), flush=True)
        if len(seen) > 1:
            print(json.dumps({"least_lateral_load": min(seen, key=lambda f: f["lateral_excess"])["driver"]}))
        return
    source = Source(args.weights, args.out)
    torch.manual_seed(args.seed)
    trainer = DreamDriver(model, cfg, args)
    arguments = {k: str(v) for k, v in sorted(vars(args).items())
                 if k not in {"out", "checkpoint", "checkpoint_every", "mode", "log_every", "steps"}}
    first = restore(args.checkpoint, trainer, arguments, CHECKPOINT_FORMAT) if args.checkpoint else 0
    n = len(states["speed"])
    print(f"{n} real starts, a driver of width {args.width}, steps {first}..{args.steps} of {args.batch} drives of "
          f"{args.horizon} decisions" + (" (resumed)" if first else ""), flush=True)
    begun, sums = time.time(), {}
    for step in range(first, args.steps):
        i = torch.randint(n, (args.batch,))
        for k, v in trainer.step(states["z"][i], states["h"][i], states["speed"][i]).items():
            sums[k] = sums.get(k, 0.0) + v
        if (step + 1) % args.log_every == 0:
            shown = ", ".join(f"{k} {v / args.log_every:.3f}" for k, v in sums.items())
            rate = args.log_every * args.batch * args.horizon / max(time.time() - begun, 1e-9)
            print(f"step {step + 1}/{args.steps}: {shown} ({time.time() - begun:.0f} s, {rate:.0f} dream decisions/s)",
                  flush=True)
            sums, begun = {}, time.time()
        if args.checkpoint and ((step + 1) % args.checkpoint_every == 0 or step + 1 == args.steps):
            save_checkpoint(args.checkpoint, trainer, step + 1, arguments, CHECKPOINT_FORMAT)
    model.policy = trainer.driver
    if not args.from_policy:
        model.pace = None  # a driver learnt from a fresh start drives at its own speed
    for p in model.parameters():
        p.requires_grad_(False)
    source.write(model, cfg, args.out)


def gain_range(text: str) -> tuple[float, float]:
    """`--steer-gain`'s LO,HI (a single number: both)."""
    parts = text.split(",")
    if len(parts) not in (1, 2):
        raise ValueError(f"expected LO,HI, got {text!r}")
    low, high = float(parts[0]), float(parts[-1])
    return low, high


def paths(text: str) -> list:
    """`--look`'s and `--average`'s comma-separated files."""
    return text.split(",")


def add_arguments(t):
    """`train.py driver`'s arguments."""
    t.add_argument("--weights", required=True, help="the world: a weight file with the texture net, the reward head "
                   "(and the value head for --value)")
    t.add_argument("--episodes", help="real recorded episodes: the dream drives' starts (not for --average)")
    t.add_argument("--out", help="where to write the world with the learnt driver as its policy")
    t.add_argument("--look", metavar="DRIVER[,DRIVER...]", type=paths,
                   help="train nothing: roll each DRIVER's policy in the dream from the "
                   "starts and print what it does there (its return, speeds, steering, braking, lateral load); "
                   "of several, name the one of least lateral load")
    t.add_argument("--average", type=paths, metavar="A,B,...",
                   help="train nothing: write the world with the mean of these drivers as its policy")
    t.add_argument("--steps", type=int, default=1500)
    t.add_argument("--batch", type=int, default=256, help="dream drives per step")
    t.add_argument("--horizon", type=int, default=40, help="decisions a dream drive lasts")
    t.add_argument("--lr", type=float, default=3e-4)
    t.add_argument("--temperature", type=float, default=1.0, help="the sampled futures' (0: the mean dream)")
    t.add_argument("--value", action="store_true", help="add the value head at the horizon")
    t.add_argument("--off-road-cost", type=float, default=0.0, help="paid per unit of off-road chance a decision")
    t.add_argument("--brake-gradient", action="store_true",
                   help="the speed response's dead band passes a gradient back (straight through)")
    t.add_argument("--lateral-cost", type=float, default=0.0,
                   help="paid per unit of lateral load (speed / 50)^2 |steering| above --lateral-limit, a decision")
    t.add_argument("--lateral-by", choices=("both", "speed"), default="both",
                   help="what the lateral cost's gradient changes: the speed and the steering, or the speed alone")
    t.add_argument("--lateral-limit", type=float, default=0.2, help="the lateral load that costs nothing")
    t.add_argument("--top-speed", type=float, default=60.0, help="the highest target speed the driver may give")
    t.add_argument("--steer-gain", type=gain_range, default=(1.0, 1.0), metavar="LO,HI",
                   help="each dream drive's steering reaches the transition times a gain drawn from LO..HI")
    t.add_argument("--first-speed", type=float, default=30.0, help="the untrained driver's target speed")
    t.add_argument("--width", type=int, default=64, help="units of the driver's layer (--from-policy: the policy's)")
    t.add_argument("--from-policy", action="store_true",
                   help="start from the file's policy (fine-tuning the clone; its pace head kept) instead of afresh")
    t.add_argument("--stay", type=float, default=0.0,
                   help="with --from-policy: paid per squared change of its outputs (target / --top-speed, steering)")
    t.add_argument("--on-road-starts", action="store_true", help="start only where the car is on the road")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--log-every", type=int, default=50)
    t.add_argument("--checkpoint", help="checkpoint file, written every --checkpoint-every steps and read back")
    t.add_argument("--checkpoint-every", type=int, default=250)

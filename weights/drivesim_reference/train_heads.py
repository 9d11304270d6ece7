"""`train.py heads`: the reward head or the value head of a weight file, trained on episodes that
carry the env's rewards (`python -m drivesim record` and `dagger` write them): the PyTorch twin of the
Rust `train heads` (examples/train/heads.rs, with regression.rs's fit and drives.rs's split).

The episodes (and, unless --no-mirror, their mirror images: frames flipped left to right, the
steering negated, after the plain ones) are encoded with the encoder's mean; the transition is
stepped from zeros along each drive with the recorded (speed, steering), so that frame t's state
is [z_t | h_t], h_t the hidden state before the step with frame t's code and action.
- reward: for t in 0..N-1, from state t+1, the targets (reward[t], 1 - on_road[t+1]).
- value: from state t, TD(λ)'s λ-return with rewards reward[t] and next values V(state t+1)
  (heads.py `lambda_returns`, per drive), recomputed with the head as trained so far every
  --refresh steps from step 0; the discount is written as `drivesim.discount`. With
  --dream-steps K, also on dreamed drives (dreams.rs's `dream`): from every --dream-every-th
  state of the training drives the policy drives on for K decisions over sampled futures, the
  reward head scoring them; each is a drive cut off after K decisions, after the real ones.
Training: heads.py's HeadTrainer in each target's mean and population deviation over the training
examples (for value, of the returns with every next value 0), at a cosine learning rate, on
batches drawn in the Rust command's seeded order (SplitMix64 shuffles). The written file is the
input with the head's four tensors put in (in the file's dtype) and, for value, the discount.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from drivesim import episodes
from drivesim_reference.heads import HeadTrainer, lambda_returns
from drivesim_reference.model import (ACTIONS_KEY, CONFIG_KEY, DISCOUNT_KEY, DISCRIMINATOR, FRAME_HZ_KEY, Head, check_discount,
                   load_drivesim, save_drivesim)
from drivesim_reference.vae_gan import to_input

ENCODE_BATCH = 256


@dataclass
class Examples:
    """A head's examples: inputs [n, z + hd] and targets [n, outputs], float32."""
    inputs: torch.Tensor
    targets: torch.Tensor

    def __len__(self):
        return len(self.inputs)

    def units(self) -> list[tuple[float, float]]:
        """Each target column's mean and population deviation (1 where it does not vary), in
        float64 and then float32, as regression.rs's `Examples::units`."""
        t = self.targets.double()
        mean = t.mean(0) if len(t) else torch.zeros(t.shape[1], dtype=torch.float64)
        var = ((t - mean) ** 2).mean(0) if len(t) else torch.zeros_like(mean)
        std = torch.where(var > 1e-12, var.sqrt(), torch.ones_like(var))
        return [(float(np.float32(m)), float(np.float32(s))) for m, s in zip(mean.tolist(), std.tolist())]


@dataclass
class HeadExamples:
    """Both heads' examples of some encoded drives, with what the value's λ-returns need."""
    reward: Examples
    value: Examples
    rewards: torch.Tensor  # [n]: each decision's reward
    next_states: torch.Tensor  # [n, z + hd]: the state each decision led to
    drive_ends: list  # the end of each drive's decisions in the rows above
    discount: float
    lam: float
    states: torch.Tensor = None  # [frames, z + hd]: every frame's state, where dreamed drives start
    speeds: torch.Tensor = None  # [frames]: the speedometer at each

    def returns(self, next_values) -> torch.Tensor:
        """Each drive's λ-returns with `next_values` [n] (a drive cut off by the recording is
        bootstrapped from its last state's value): set as the value's targets."""
        out, start = torch.empty(len(self.rewards)), 0
        for end in self.drive_ends:
            out[start:end] = lambda_returns(self.rewards[start:end], next_values[start:end],
                                            self.discount, self.lam)
            start = end
        self.value.targets = out[:, None]
        return out

    def add(self, dreams: "Dreams"):
        """Dreamed drives added to the value's examples, after the real ones (heads.rs's `add`),
        each a drive cut off; the value's targets the returns with every next value 0 again."""
        base = len(self.rewards)
        self.value.inputs = torch.cat([self.value.inputs, dreams.inputs])
        self.next_states = torch.cat([self.next_states, dreams.next_states])  # the reward's inputs kept
        self.rewards = torch.cat([self.rewards, dreams.rewards])
        self.drive_ends = self.drive_ends + [base + e for e in dreams.ends]
        self.returns(torch.zeros(len(self.rewards)))


class Order:
    """The order the examples are drawn in (regression.rs's `Order`): each pass over them the
    last pass's order shuffled again (Fisher-Yates from the end), from a SplitMix64 generator
    seeded with `seed`; the first pass shuffles 0..count."""
    MASK = (1 << 64) - 1
    GOLDEN, M1, M2 = 0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB

    def __init__(self, count: int, seed: int):
        self.order, self.next, self.state = np.arange(count), count, seed & self.MASK

    def shuffle(self):
        n = len(self.order)
        if n < 2:
            return
        u = np.uint64
        with np.errstate(over="ignore"):
            x = u(self.state) + np.arange(1, n, dtype=u) * u(self.GOLDEN)
            x = (x ^ (x >> u(30))) * u(self.M1)
            x = (x ^ (x >> u(27))) * u(self.M2)
        x ^= x >> u(31)
        swap_with = (x % np.arange(n, 1, -1, dtype=u)).tolist()  # draw k is for i = n - 1 - k
        self.state = (self.state + (n - 1) * self.GOLDEN) & self.MASK
        order = self.order.tolist()
        for i, j in zip(range(n - 1, 0, -1), swap_with):
            order[i], order[j] = order[j], order[i]
        self.order = np.array(order)

    def draw(self, batch: int) -> np.ndarray:
        """The next `batch` examples' indices."""
        out = []
        while batch:
            if self.next == len(self.order):
                self.shuffle()
                self.next = 0
            take = min(batch, len(self.order) - self.next)
            out.append(self.order[self.next:self.next + take])
            self.next, batch = self.next + take, batch - take
        return np.concatenate(out)


def cosine_lr(base: float, step: int, steps: int) -> float:
    """The crate's `cosine_lr`: base (1 + cos(π step / steps)) / 2, to float32."""
    progress = min(step, steps) / max(steps, 1)
    return float(np.float32(base * (1.0 + math.cos(math.pi * progress)) / 2.0))


@torch.no_grad()
def encode_view(model, data: episodes.Episodes, mirrored: bool):
    """Every frame's code (the encoder's mean), of the frames as they are or flipped left to
    right, and the actions with the steering negated in a mirror (examples/common.rs's
    `encode_view`, drivesim.episodes' `with_mirror_images`)."""
    codes = []
    for s in range(0, len(data.frames), ENCODE_BATCH):
        frames = data.frames[s:s + ENCODE_BATCH]
        frames = frames[:, :, ::-1] if mirrored else frames
        codes.append(model.encoder(to_input(torch.from_numpy(np.array(frames))))[0])
    actions = data.actions.copy()
    if mirrored:
        actions[:, 1] *= -1
    return torch.cat(codes), torch.from_numpy(actions)


def views(model, data: episodes.Episodes, no_mirror: bool) -> list:
    """The drives of `data`: (codes, actions, reward, on_road) of each episode, then (unless
    `no_mirror`) of each episode's mirror image, in the same order."""
    drives = []
    for mirrored in (False,) if no_mirror else (False, True):
        codes, actions = encode_view(model, data, mirrored)
        for s, e in data.bounds():
            drives.append((codes[s:e], actions[s:e], torch.tensor(data.rewards["reward"][s:e]),
                           torch.tensor(data.rewards["on_road"][s:e])))
    return drives


def load_episodes(path, cfg, what: str, rewards: bool = True) -> episodes.Episodes:
    """Episodes whose frames and actions `cfg`'s model takes (with `rewards`: rewards too)."""
    data = episodes.read(path)
    if rewards and data.rewards is None:
        raise ValueError(f"{what} {path}: episodes without rewards (`reward`, `on_road`): record them "
                         "again with `python -m drivesim record` (or `dagger`), which writes them")
    h, w, c = data.frames.shape[1:]
    if (h, w, c) != (cfg.height, cfg.width, cfg.channels) or cfg.action_dim != 2:
        raise ValueError(f"{what} {path}: {h}x{w}x{c} frames with 2 actions, the model takes "
                         f"{cfg.height}x{cfg.width}x{cfg.channels} with {cfg.action_dim}")
    return data


def split(model, cfg, args):
    """The training and held-out drives: every view of the --heldout file's episodes, or of the
    last --holdout episodes of --episodes (their mirror images held out with them)."""
    data = load_episodes(args.episodes, cfg, "episodes")
    other = load_episodes(args.heldout, cfg, "held-out episodes") if args.heldout else None
    train = views(model, data, args.no_mirror)
    if other is not None:
        return train, views(model, other, args.no_mirror)
    count, holdout = len(data), args.holdout
    if not 0 <= holdout < count:
        raise ValueError(f"--holdout {holdout} leaves no training episode" if holdout >= count
                         else f"--holdout must be at least 0, got {holdout}")
    heldout = []
    for view in reversed(range(len(train) // count)):
        end = (view + 1) * count
        heldout.extend(train[end - holdout:end])
        del train[end - holdout:end]
    return train, heldout


@torch.no_grad()
def states(transition, drives, hidden_dim: int) -> list:
    """Each drive's states [frames, z + hd]: [z_t | h_t], h_t the hidden state before the step
    with frame t's code and action (the transition stepped from zeros; the drives side by side)."""
    if not drives:
        return []
    longest = max(len(d[0]) for d in drives)
    z = torch.zeros(len(drives), longest, drives[0][0].shape[1])
    c = torch.zeros(len(drives), longest, 2)
    for i, (codes, actions, *_) in enumerate(drives):
        z[i, :len(codes)], c[i, :len(codes)] = codes, actions
    h, hs = torch.zeros(len(drives), hidden_dim), []
    for t in range(longest):
        hs.append(h)
        h = transition(z[:, t], h, c[:, t])[1]
    hs = torch.stack(hs, 1)
    return [torch.cat([z[i, :len(d[0])], hs[i, :len(d[0])]], 1) for i, d in enumerate(drives)]


def _cat(parts, *shape):
    return torch.cat(parts) if parts else torch.zeros(0, *shape)


def examples(model, cfg, drives, discount: float, lam: float) -> HeadExamples:
    """The heads' examples of `drives` (heads.rs's `examples`); the value's targets are the
    returns with every next value 0 (the units' targets)."""
    width = cfg.z_dim + cfg.hidden_dim
    inputs, nexts, reward_targets, rewards, ends = [], [], [], [], []
    end, along = 0, states(model.transition, drives, cfg.hidden_dim)
    for s, (_, _, reward, on_road) in zip(along, drives):
        inputs.append(s[:-1])
        nexts.append(s[1:])
        reward_targets.append(torch.stack([reward[:-1], 1.0 - on_road[1:].float()], 1))
        rewards.append(reward[:-1])
        end += len(rewards[-1])
        ends.append(end)
    next_states = _cat(nexts, width)
    out = HeadExamples(Examples(next_states, _cat(reward_targets, 2)), Examples(_cat(inputs, width), None),
                       _cat(rewards), next_states, ends, discount, lam, _cat(along, width),
                       _cat([d[1][:, 0] for d in drives]))
    out.returns(torch.zeros(len(out.rewards)))
    return out


DREAM_BATCH = 256


@dataclass
class Dreams:
    """Dreamed drives (dreams.rs's `Dreams`): each decision's state [n, z + hd], its predicted
    reward [n], the state it led to [n, z + hd], and where each drive ends (counted in decisions)."""
    inputs: torch.Tensor
    rewards: torch.Tensor
    next_states: torch.Tensor
    ends: list


def action_ranges(meta: dict):
    """Each action's (min, max) of `drivesim.actions` as float32 tensors, what the crate's
    `Simulator::act` clips the policy's actions to; None without the metadata (no clipping)."""
    if ACTIONS_KEY not in meta:
        return None
    specs = json.loads(meta[ACTIONS_KEY])
    return tuple(torch.tensor([np.float32(a[k]) for a in specs]) for k in ("min", "max"))


@torch.no_grad()
def dream(model, cfg, states: torch.Tensor, speeds: torch.Tensor, steps: int, every: int, seed: int,
          ranges=None) -> Dreams:
    """Drives of `steps` decisions from every `every`-th of the real `states` ([z | h] rows, the
    speedometer at each in `speeds`), DREAM_BATCH at a time (dreams.rs's `dream`): at each step
    the policy's (target, steering), clipped to `ranges`, steers the transition driven at the
    speed reached (the start's speedometer, then the last target); the predicted code is sampled
    at temperature 1 (`mean + exp(S h' + s) * L eps`, eps from a generator seeded with seed +
    batch, not the crate's counter-based draws) and the reward head's reward of the new state is
    the decision's."""
    heads = model.heads()
    if "policy" not in heads or "reward" not in heads:
        raise ValueError("dreamed drives need the model's policy and reward head (train heads --head reward first)")
    transition, zd = model.transition, cfg.z_dim
    if not transition.spread:
        raise ValueError("dreamed drives sample their futures, and the model's transition predicts no spread "
                         "(no `transition.S` and `transition.s` in its weight file)")
    inputs, rewards, nexts, ends = [], [], [], []
    starts = torch.arange(0, len(speeds), max(every, 1))
    for b, batch in enumerate(starts.split(DREAM_BATCH)):
        generator = torch.Generator().manual_seed((seed + b) & Order.MASK)
        z, h, speed = states[batch, :zd], states[batch, zd:], speeds[batch]
        rows, scores = [], []
        for t in range(steps + 1):
            rows.append(torch.cat([z, h], 1))
            if t == steps:
                break
            act = model.policy(z, h)
            if ranges is not None:
                act = act.clamp(ranges[0], ranges[1])
            # The transition reads the speed driven, the policy gives the target.
            z, h = transition(z, h, torch.stack([speed, act[:, 1]], 1))
            speed = act[:, 0]
            noise = torch.randn(z.shape, generator=generator)
            if transition.correlated:
                noise = noise @ transition.L.T
            z = z + transition.log_sigma(h).clamp(-20, 20).exp() * noise
            scores.append(model.reward(z, h)[:, 0])
        rows = torch.stack(rows, 1)  # [drive, step, z + hd]
        inputs.append(rows[:, :-1].flatten(0, 1))
        nexts.append(rows[:, 1:].flatten(0, 1))
        rewards.append(torch.stack(scores, 1).flatten() if steps else torch.zeros(0))
        base = ends[-1] if ends else 0
        ends.extend(base + steps * (k + 1) for k in range(len(batch)))
    width = cfg.z_dim + cfg.hidden_dim
    return Dreams(_cat(inputs, width), _cat(rewards), _cat(nexts, width), ends)


@torch.no_grad()
def predict(head: Head, inputs: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The head, its tensors rounded to the weight file's `dtype` (as the crate reads the file it
    writes), on each input; the reward head's off-road chance clamped to [0, 1] as the crate's."""
    w1, b1, w2, b2 = (p.detach().to(dtype).float() for p in (head.hidden.weight, head.hidden.bias,
                                                               head.output.weight, head.output.bias))
    out = torch.cat([torch.tanh(x @ w1.T + b1) @ w2.T + b2 for x in inputs.split(4096)]) if len(inputs) \
        else torch.zeros(0, head.outputs)
    if head.kind == "reward":
        out[:, 1].clamp_(0.0, 1.0)
    return out


def report(kind, head, heldout: HeadExamples, dtype, when: str):
    """The held-out RMS errors, as the Rust command prints them."""
    if head is None or not len(heldout.rewards):
        return
    if kind == "reward":
        ex = heldout.reward
        rms = ((predict(head, ex.inputs, dtype).double() - ex.targets.double()) ** 2).mean(0).sqrt().tolist()
        spread = ex.units()
        print(f"held out, {when}: RMS error reward {rms[0]:.3f} (targets' deviation {spread[0][1]:.3f}), "
              f"off the road {rms[1]:.3f} ({spread[1][1]:.3f})", flush=True)
    else:
        heldout.returns(predict(head, heldout.next_states, dtype)[:, 0])
        ex = heldout.value
        rms = ((predict(head, ex.inputs, dtype).double() - ex.targets.double()) ** 2).mean().sqrt().item()
        print(f"held out, {when}: RMS error against the λ-returns {rms:.2f} (their deviation "
              f"{ex.units()[0][1]:.2f})", flush=True)


class _Stored(torch.nn.Module):
    """The file's discriminator tensors as they are, for save_drivesim to write back."""

    def __init__(self, tensors):
        super().__init__()
        self.stored = tensors

    def state_dict(self, *args, **kwargs):
        return dict(self.stored)


class Source:
    """The weight file a trainer starts from (its dtype, metadata and discriminator), and
    `write`: a trained model written as that file was, in its dtype, with its metadata (a
    warning names metadata the crate does not read, which is not written) and its
    discriminator."""

    def __init__(self, path, out):
        self.stored = load_file(str(path))
        self.dtype = next(iter(self.stored.values())).dtype
        with safe_open(str(path), "pt") as f:
            self.meta = f.metadata() or {}
        unknown = sorted(set(self.meta) - {CONFIG_KEY, ACTIONS_KEY, FRAME_HZ_KEY, DISCOUNT_KEY})
        if unknown:
            print(f"warning: {path}: metadata {unknown} is not written to {out}", flush=True)

    def write(self, model, cfg, out, discount=None):
        """`model` to `out`; `discount` (default: the model's) as `drivesim.discount`."""
        hz, meta = self.meta.get(FRAME_HZ_KEY), self.meta
        discriminator = {k[len(DISCRIMINATOR):]: v for k, v in self.stored.items() if k.startswith(DISCRIMINATOR)}
        save_drivesim(model, cfg, out, self.dtype, actions=json.loads(meta[ACTIONS_KEY]) if ACTIONS_KEY in meta
                      else None, discriminator=_Stored(discriminator) if discriminator else None,
                      frame_hz=float(hz) if hz else None, discount=discount)
        print(f"wrote {out}", flush=True)


def check(args):
    if args.steps < 0 or not 1 <= args.batch <= 65536 or args.width < 1 or args.refresh < 1:
        raise ValueError("--steps must be at least 0, --batch from 1 to 65536, --width and --refresh at least 1")
    if not (math.isfinite(args.lr) and args.lr > 0):
        raise ValueError(f"--lr must be a finite number above 0, got {args.lr}")
    if not 0.0 <= args.lam <= 1.0:
        raise ValueError(f"--lambda must be from 0 to 1, got {args.lam}")
    if args.dream_steps < 0 or args.dream_every < 1:
        raise ValueError("--dream-steps must be at least 0, --dream-every at least 1")
    if args.head == "value":
        check_discount(args.discount)


def heads(args):
    check(args)
    kind = args.head
    model, cfg = load_drivesim(args.weights)
    source = Source(args.weights, args.out)
    dtype, meta = source.dtype, source.meta
    old = model.heads().get(kind)
    if (args.restart or old is None) and not 1 <= args.width <= cfg.hidden_dim:
        raise ValueError(f"--width {args.width}: a new head's width must be from 1 to the model's hidden_dim "
                         f"({cfg.hidden_dim}), as the crate reads it")
    train_drives, heldout_drives = split(model, cfg, args)
    train = examples(model, cfg, train_drives, args.discount, args.lam)
    heldout = examples(model, cfg, heldout_drives, args.discount, args.lam)
    if kind == "value" and args.dream_steps > 0:
        dreams = dream(model, cfg, train.states, train.speeds, args.dream_steps, args.dream_every, args.seed,
                       action_ranges(meta))
        print(f"{len(dreams.ends)} dreamed drives of {args.dream_steps} decisions from real states", flush=True)
        train.add(dreams)
    ex = train.reward if kind == "reward" else train.value
    if not len(ex):
        raise ValueError("no examples to train on (every training episode is a single frame)")
    units = ex.units()
    if args.restart or old is None:
        torch.manual_seed(args.seed)
        head = Head(cfg, args.width, kind)
    else:
        head = Head(cfg, old.width, kind)
        head.load_state_dict(old.state_dict())
    trainer = HeadTrainer(head, units)
    batch = min(args.batch, len(ex))
    shown = ", ".join(f"({np.float32(m)}, {np.float32(s)})" for m, s in units)
    print(f"{len(ex)} examples ({len(heldout.rewards)} held out), {kind} head width {head.width}, targets' mean "
          f"and deviation [{shown}], {args.steps} steps of {args.batch}", flush=True)
    report(kind, old, heldout, dtype, "before")
    order, loss_sum, start = Order(len(ex), args.seed), 0.0, time.time()
    for step in range(args.steps):
        if kind == "value" and step % args.refresh == 0:
            train.returns(predict(head, train.next_states, dtype)[:, 0])
        i = torch.from_numpy(order.draw(batch))
        loss_sum += trainer.step(ex.inputs[i], ex.targets[i], cosine_lr(args.lr, step, args.steps))
        if (step + 1) % 500 == 0:
            print(f"step {step + 1}/{args.steps}: loss {loss_sum / 500:.4f}", flush=True)
            loss_sum = 0.0
    print(f"trained in {time.time() - start:.1f} s", flush=True)
    report(kind, head, heldout, dtype, "after")
    setattr(model, kind, head)
    source.write(model, cfg, args.out, discount=args.discount if kind == "value" else None)

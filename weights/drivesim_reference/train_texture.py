"""`train.py texture`: the transition's texture net (model.py `Texture`, the crate's texture.rs),
trained adversarially so that sampled futures keep the road's kerbs and grass patches, which a
mean prediction loses within a few steps and Gaussian noise around it does not bring back
(docs/fidelity.md). Every other tensor of the file stays as it was: the mean path (temperature 0)
and every agent on it are unchanged.

The episodes (and, unless --no-mirror, their mirror images) are encoded with the encoder's mean.
Each step draws --batch windows of 5 recorded codes and --fed more: the transition is stepped
along the window (the recorded codes first, then its own samples fed back, detached), each step
sampled as `A h' + a + texture(noise, h')`. Three discriminators judge the samples, each against
the recorded codes at the same steps, and the texture net learns to fool them (non-saturating GAN
losses), with weights:
- --latent: a two-layer network on `[code | h']`, at the recorded steps 1 to 4 (h' has seen
  recorded codes only): the sample is a plausible next code for the state;
- --image: the VAE-GAN's discriminator architecture on the generated frames of --frames fed-back
  steps per window (the recorded codes' reconstructions are the real frames): the frames look
  like the road's, kerbs included;
- --marginal: a two-layer network on the codes of every fed-back step: the dreamed codes keep
  the real codes' distribution as the drive goes on;
- --pairs (0 unless given): a two-layer network on `[code | next code | action]` at every fed-back
  step: each dreamed step is one the road could take under that action, however long the dream
  has run on its own samples (a road that ends or jumps is not);
and --bestof: the smallest squared error of 8 samples at step 4, which keeps one of a few
samples near what happened. With --from-model the texture net starts from the file's own (a
fine-tuning of, say, `train latent`'s, on the futures it draws itself), else from the mean. Adam
(lr --lr, betas 0.5 and 0.999) for the texture net and the discriminators alike.

With --checkpoint FILE the run writes everything it needs every --checkpoint-every steps
(atomically) and a run started again with the same arguments goes on from there to the same
bytes (on the same device); --steps may differ (no schedule depends on it), so a run can also
be taken further. The written file is the input with `transition.texture.*` put in,
in the file's dtype.
"""

from __future__ import annotations

import io
import math
import time

import torch
from safetensors import safe_open
from torch import nn
from torch.nn import functional as F

from drivesim import _files
from drivesim_reference.model import TEXTURE, Texture, load_drivesim
from drivesim_reference.sequences import TEACHER
from drivesim_reference.train_heads import Source, encode_view, load_episodes
from drivesim_reference.vae_gan import Discriminator
CHECKPOINT_FORMAT = "drivesim train.py texture checkpoint 1"
# Samples per window of the --bestof term.
BEST_OF = 8


class Critic(nn.Module):
    """A discriminator of codes (or `[code | h']`): one leaky-ReLU layer, then the logit."""

    def __init__(self, inputs: int, width: int):
        super().__init__()
        self.hidden, self.output = nn.Linear(inputs, width), nn.Linear(width, 1)

    def forward(self, x):
        return self.output(F.leaky_relu(self.hidden(x), 0.2)).squeeze(1)


class TextureGAN:
    """The texture net and its three discriminators, one adversarial step at a time."""

    def __init__(self, model, cfg, args, device):
        self.model, self.args, self.device = model, args, device
        zd, hd = cfg.z_dim, cfg.hidden_dim
        self.texture = own_texture(model, cfg, device) if args.from_model else Texture(cfg, args.width).to(device)
        self.latent, self.marginal = Critic(zd + hd, args.width).to(device), Critic(zd, args.width).to(device)
        self.image = Discriminator(cfg).to(device)
        # Made only where asked: a run without it draws the same random numbers as before it was.
        self.pairs = Critic(2 * zd + cfg.action_dim, args.width).to(device) if args.pairs else None
        adam = dict(lr=args.lr, betas=(0.5, 0.999))
        self.opt_texture = torch.optim.Adam(self.texture.parameters(), **adam)
        critics = [*self.latent.parameters(), *self.marginal.parameters(), *self.image.parameters(),
                   *(self.pairs.parameters() if self.pairs else [])]
        self.opt_critics = torch.optim.Adam(critics, **adam)

    def modules(self):
        return dict(texture=self.texture, latent=self.latent, marginal=self.marginal, image=self.image,
                    opt_texture=self.opt_texture, opt_critics=self.opt_critics,
                    **(dict(pairs=self.pairs) if self.pairs else {}))

    def sample(self, mean, h):
        return mean + self.texture(torch.randn(mean.shape, device=self.device), h)

    def step(self, z, c) -> dict:
        """One step on windows of codes z [B, T, z] and actions c [B, T-1, 2]."""
        a, tr = self.args, self.model.transition
        b, steps = z.shape[0], z.shape[1] - 1
        h = z.new_zeros(b, tr.W.shape[0])
        drawn, hs, means = [], [], []
        for t in range(steps):
            mean, h = tr(z[:, t] if t < TEACHER else drawn[-1].detach(), h, c[:, t])
            drawn.append(self.sample(mean, h))
            hs.append(h)
            means.append(mean)
        recorded = slice(1, TEACHER)  # steps whose h has seen recorded codes only
        state = torch.cat(hs[recorded])
        fake_l, real_l = torch.cat(drawn[recorded]), torch.cat([z[:, t + 1] for t in range(1, TEACHER)])
        fed = range(TEACHER, steps)
        fake_m, real_m = torch.cat([drawn[t] for t in fed]), torch.cat([z[:, t + 1] for t in fed])
        shown = torch.randint(TEACHER, steps, (a.frames,)).tolist()
        fake_i = self.model.generator(torch.cat([drawn[t] for t in shown]))
        with torch.no_grad():
            real_i = self.model.generator(torch.cat([z[:, t + 1] for t in shown]))

        def judged(critic_out, real: bool):
            return F.binary_cross_entropy_with_logits(critic_out, torch.full_like(critic_out, float(real)))

        if self.pairs:  # each fed-back step: the code it started from, the one it drew, the action
            real_p = torch.cat([torch.cat([z[:, t], z[:, t + 1], c[:, t]], 1) for t in fed])
            fake_p = torch.cat([torch.cat([drawn[t - 1], drawn[t], c[:, t]], 1) for t in fed])
        critics = (judged(self.latent(torch.cat([real_l, state], 1)), True)
                   + judged(self.latent(torch.cat([fake_l.detach(), state], 1)), False)
                   + judged(self.marginal(real_m), True) + judged(self.marginal(fake_m.detach()), False)
                   + judged(self.image(real_i)[0], True) + judged(self.image(fake_i.detach())[0], False))
        if self.pairs:
            critics = critics + judged(self.pairs(real_p), True) + judged(self.pairs(fake_p.detach()), False)
        self.opt_critics.zero_grad()
        critics.backward()
        self.opt_critics.step()

        last = TEACHER - 1
        several = self.sample(means[last].detach().repeat(BEST_OF, 1), hs[last].detach().repeat(BEST_OF, 1))
        best = (several - z[:, TEACHER].repeat(BEST_OF, 1)).square().mean(1).view(BEST_OF, b).min(0).values.mean()
        terms = dict(latent=judged(self.latent(torch.cat([fake_l, state], 1)), True),
                     image=judged(self.image(fake_i)[0], True), marginal=judged(self.marginal(fake_m), True),
                     bestof=best)
        if self.pairs:
            terms["pairs"] = judged(self.pairs(fake_p), True)
        loss = sum(getattr(a, k) * v for k, v in terms.items())
        self.opt_texture.zero_grad()
        loss.backward()
        self.opt_texture.step()
        return dict(critics=float(critics.detach()), **{k: float(v.detach()) for k, v in terms.items()})


def check(args):
    if args.steps < 0 or not 1 <= args.batch <= 65536 or args.fed < 1 or args.frames < 1:
        raise ValueError("--steps must be at least 0, --batch from 1 to 65536, --fed and --frames at least 1")
    for name in ("lr", "latent", "image", "marginal", "bestof", "pairs"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value >= 0) or (name == "lr" and value == 0):
            raise ValueError(f"--{name} must be a finite number at least 0 (--lr above 0), got {value}")


def check_has_texture(path):
    """--from-model's file must have a texture net: said before the episodes are encoded (minutes),
    from the file's header alone (a file that is not safetensors is the loader's to report)."""
    try:
        with safe_open(path, "pt") as f:
            present = TEXTURE + "hidden.bias" in f.keys()
    except Exception:  # noqa: BLE001 - load_drivesim reports what is wrong with it
        return
    if not present:
        raise ValueError(f"--from-model: {path} has no texture net ({TEXTURE}*) to start from")


def own_texture(model, cfg, device):
    """A trainable copy of the file's own texture net (--from-model, `check_has_texture`), at its
    own width."""
    own = model.transition.texture
    texture = Texture(cfg, own.hidden.out_features)
    texture.load_state_dict(own.state_dict())
    return texture.to(device)


def windows(model, data, length: int, no_mirror: bool):
    """Every view's codes and actions, one array each, and the starts of its windows of `length`."""
    codes, actions, starts = [], [], []
    offset = 0
    for mirrored in (False,) if no_mirror else (False, True):
        z, c = encode_view(model, data, mirrored)
        codes.append(z)
        actions.append(c)
        starts += [offset + t for s, e in data.bounds() for t in range(s, e - length + 1)]
        offset += len(z)
    if not starts:
        raise ValueError(f"no episode is long enough for a window of {length} frames (5 recorded, --fed more)")
    return torch.cat(codes), torch.cat(actions), torch.tensor(starts)


def save_checkpoint(path, gan, step: int, arguments: dict, fmt: str = CHECKPOINT_FORMAT):
    """Writes `gan.modules()`' states, the step and the random state to `path` (atomically)."""
    state = dict(format=fmt, arguments=arguments, step=step,
                 modules={k: m.state_dict() for k, m in gan.modules().items()},
                 random=dict(torch=torch.get_rng_state(),
                             cuda=torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None))
    blob = _bytes(state)
    with _files.atomic_write(path) as f:
        f.write(blob)


def _bytes(state) -> bytes:
    buf = io.BytesIO()
    torch.save(state, buf)
    return buf.getvalue()


def restore(path, gan, arguments: dict, fmt: str = CHECKPOINT_FORMAT) -> int:
    """The step a checkpoint at `path` was written after (0 where there is none), `gan.modules()`
    and the random state restored from it."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        return 0
    if state.get("format") != fmt or state.get("arguments") != arguments:
        raise ValueError(f"{path}: a checkpoint of another run (other arguments): remove it or name another file")
    for k, m in gan.modules().items():
        m.load_state_dict(state["modules"][k])
    torch.set_rng_state(state["random"]["torch"])
    if state["random"]["cuda"] is not None:
        torch.cuda.set_rng_state_all(state["random"]["cuda"])
    return state["step"]


def texture(args):
    check(args)
    if args.from_model:
        check_has_texture(args.weights)
    train_sampler(args, TextureGAN, CHECKPOINT_FORMAT)


def train_sampler(args, make, fmt: str):
    """The run `train.py texture`, `latent` and `steering` share: the file and the episodes read,
    the windows encoded, the trainer `make(model, cfg, args, device)` made (with `step(z, c)` ->
    the losses, `modules()` and `texture`) and stepped, resumed from and checkpointed to
    `args.checkpoint` (format `fmt`), and the input written again with the trainer's texture net
    (None: the model's own, as `steering` keeps it)."""
    if args.checkpoint_every < 1:  # add_run_arguments' flag, checked here for every trainer that shares it
        raise ValueError("--checkpoint-every must be at least 1")
    model, cfg = load_drivesim(args.weights)
    source = Source(args.weights, args.out)
    if getattr(args, "width", None) is not None and not 1 <= args.width <= cfg.hidden_dim:  # a texture net made
        raise ValueError(f"--width {args.width}: from 1 to the model's hidden_dim ({cfg.hidden_dim}), as the crate "
                         "reads it")
    data = load_episodes(args.episodes, cfg, "episodes", rewards=False)
    dev = torch.device(args.device)
    with torch.no_grad():
        codes, actions, starts = windows(model, data, TEACHER + args.fed + 1, args.no_mirror)
    model = model.to(dev)
    for p in model.parameters():
        p.requires_grad_(False)
    codes, actions = codes.to(dev), actions.to(dev)
    torch.manual_seed(args.seed)
    trainer = make(model, cfg, args, dev)
    arguments = {k: str(v) for k, v in sorted(vars(args).items())
                 if k not in {"out", "checkpoint", "checkpoint_every", "mode", "device", "log_every", "steps"}}
    first = restore(args.checkpoint, trainer, arguments, fmt) if args.checkpoint else 0
    made = f", texture net width {args.width}" if getattr(args, "width", None) is not None else ""
    print(f"{len(starts)} windows of {TEACHER} + {args.fed} codes{made}, "
          f"steps {first}..{args.steps} of {args.batch}" + (" (resumed)" if first else ""), flush=True)
    span = torch.arange(TEACHER + args.fed + 1, device=dev)
    begun, sums = time.time(), {}
    for step in range(first, args.steps):
        idx = starts[torch.randint(len(starts), (args.batch,))].to(dev)[:, None] + span
        for k, v in trainer.step(codes[idx], actions[idx[:, :-1]]).items():
            sums[k] = sums.get(k, 0.0) + v
        if (step + 1) % args.log_every == 0:
            shown = ", ".join(f"{k} {v / args.log_every:.3f}" for k, v in sums.items())
            print(f"step {step + 1}/{args.steps}: {shown} ({time.time() - begun:.0f} s)", flush=True)
            sums = {}
        if args.checkpoint and ((step + 1) % args.checkpoint_every == 0 or step + 1 == args.steps):
            save_checkpoint(args.checkpoint, trainer, step + 1, arguments, fmt)
    if trainer.texture is not None:  # `train.py steering` keeps the model's own, or none
        model.transition.texture = trainer.texture
    for p in model.parameters():
        p.requires_grad_(False)
    source.write(model.cpu(), cfg, args.out)


def add_arguments(t):
    """`train.py texture`'s arguments."""
    t.add_argument("--weights", required=True, help="weight file to start from (every tensor of it is kept)")
    t.add_argument("--episodes", required=True, help="episodes to learn the road's texture from")
    t.add_argument("--out", required=True, help="where to write the weights with the texture net")
    t.add_argument("--fed", type=int, default=20, help="fed-back sampled steps per window")
    t.add_argument("--frames", type=int, default=4, help="fed-back steps per window the image discriminator judges")
    t.add_argument("--width", type=int, default=256, help="units of the texture net's and the code critics' layer")
    t.add_argument("--lr", type=float, default=2e-4)
    t.add_argument("--latent", type=float, default=1.0, help="weight of the [code | h'] critic's term")
    t.add_argument("--image", type=float, default=0.1, help="weight of the image discriminator's term")
    t.add_argument("--marginal", type=float, default=1.0, help="weight of the fed-back codes' critic's term")
    t.add_argument("--bestof", type=float, default=3.0, help="weight of the best of 8 samples' squared error")
    t.add_argument("--pairs", type=float, default=0.0,
                   help="weight of the fed-back steps' critic of [code | next code | action] (0: none)")
    t.add_argument("--from-model", action="store_true",
                   help="start from the file's own texture net (its width) instead of the mean")
    add_run_arguments(t)


def add_run_arguments(t):
    """The arguments of `train_sampler`'s run that `train.py texture` and `train.py latent` share."""
    t.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    t.add_argument("--steps", type=int, default=3000)
    t.add_argument("--batch", type=int, default=64, help="windows per step")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--log-every", type=int, default=250)
    t.add_argument("--no-mirror", action="store_true", help="train on the episodes only, not also on their mirror "
                   "images (frames flipped left to right, steering negated)")
    t.add_argument("--checkpoint", help="checkpoint file, written every --checkpoint-every steps and read back")
    t.add_argument("--checkpoint-every", type=int, default=500)

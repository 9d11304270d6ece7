"""`train.py latent`: the transition and its texture net (model.py `Texture`) trained together as a
conditional VAE, so that sampled futures draw the road the state cannot know: the bend that is
not in the frame yet, the grass a late driver runs onto (docs/judging.md, "A world that draws
its futures"). A sample is the crate's `A h' + a + texture(temperature * noise, h')`, the file
format unchanged: the trained file is sampled at temperature 1 (`Simulator.set_sampling`).

Each step draws --batch windows of 5 recorded codes and --fed more. The transition steps along
each window, from the recorded codes first, then from its own samples fed back (not detached:
the gradient runs through the whole window). At every step the noise is drawn from a posterior
`q(noise | h', z_next - A h' - a)` (a tanh layer of --posterior-width units, the mean and the log
standard deviation of every draw), and the loss is the squared error of the sample against the
recorded next code plus --beta times the KL divergence of the posterior from the standard normal
draws the crate samples, per code dimension. The posterior is training's alone: the file has no
place for it (a checkpoint keeps it). With --freeze-transition only the texture net learns.

--mean-weight M adds M times the squared error of the mean `A h' + a` itself against the recorded
next code. The posterior sees that code, so without it the noise can carry what the action did:
the mean world then barely answers the steering, and the sampled ones answer it by chance
(docs/judging.md, "The mean kept honest: TM"). With it, what the state and the action determine
stays in the transition, and the texture net draws what they cannot.

Adam (lr --lr) for everything, the gradient's norm clipped to 1. With --checkpoint FILE the run
writes what it needs every --checkpoint-every steps (atomically) and a run started again with the
same arguments goes on from there to the same bytes (on the same device). The written file is the
input with the transition's tensors trained and `transition.texture.*` put in, in the file's
dtype; every other tensor stays as it was.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from drivesim_reference.model import Texture
from drivesim_reference.sequences import TEACHER
from drivesim_reference.train_texture import add_run_arguments, train_sampler

CHECKPOINT_FORMAT = "drivesim train.py latent checkpoint 1"
# The posterior's log standard deviation is kept in this range (the KL term's exp stays finite).
LOG_SD = (-6.0, 2.0)


def kl_from_standard(mean: torch.Tensor, log_sd: torch.Tensor) -> torch.Tensor:
    """KL(N(mean, exp(log_sd)^2) || N(0, 1)), summed over the last dimension."""
    return (0.5 * (mean.square() + torch.exp(2 * log_sd) - 1) - log_sd).sum(-1)


class LatentTrainer:
    """The transition, its texture net and the posterior over the texture net's noise."""

    def __init__(self, model, cfg, args, device):
        self.model, self.args = model, args
        zd, hd = cfg.z_dim, cfg.hidden_dim
        self.texture = Texture(cfg, args.width).to(device)
        self.posterior = nn.Sequential(nn.Linear(hd + zd, args.posterior_width), nn.Tanh(),
                                       nn.Linear(args.posterior_width, 2 * zd)).to(device)
        learnt = [*self.texture.parameters(), *self.posterior.parameters()]
        if not args.freeze_transition:  # the model's tensors come frozen (train_sampler): these learn
            for name in ("W", "V", "U", "b", "A", "a"):
                getattr(model.transition, name).requires_grad_(True)
                learnt.append(getattr(model.transition, name))
        self.learnt = learnt
        self.opt = torch.optim.Adam(learnt, lr=args.lr)

    def modules(self):
        return dict(transition=self.model.transition, texture=self.texture, posterior=self.posterior, opt=self.opt)

    def loss(self, z, c) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The mean squared error of the samples, the mean KL per code dimension and the mean
        squared error of the means, on windows of codes z [B, T, z] and actions c [B, T-1, 2]."""
        tr = self.model.transition
        h = z.new_zeros(z.shape[0], tr.W.shape[0])
        errors, kls, means, drawn = [], [], [], None
        for t in range(z.shape[1] - 1):
            mean, h = tr(z[:, t] if t < TEACHER else drawn, h, c[:, t])
            q_mean, q_log_sd = self.posterior(torch.cat([h, z[:, t + 1] - mean], 1)).chunk(2, 1)
            q_log_sd = q_log_sd.clamp(*LOG_SD)
            noise = q_mean + torch.exp(q_log_sd) * torch.randn_like(q_mean)
            drawn = mean + self.texture(noise, h)
            errors.append(F.mse_loss(drawn, z[:, t + 1]))
            kls.append(kl_from_standard(q_mean, q_log_sd).mean())
            means.append(F.mse_loss(mean, z[:, t + 1]))
        return torch.stack(errors).mean(), torch.stack(kls).mean() / z.shape[2], torch.stack(means).mean()

    def step(self, z, c) -> dict:
        error, kl, mean_error = self.loss(z, c)
        self.opt.zero_grad()
        (error + self.args.beta * kl + self.args.mean_weight * mean_error).backward()
        nn.utils.clip_grad_norm_(self.learnt, 1.0)
        self.opt.step()
        out = dict(error=float(error.detach()), kl=float(kl.detach()))
        if self.args.mean_weight:
            out["mean_error"] = float(mean_error.detach())
        return out


def check(args):
    if args.steps < 0 or not 1 <= args.batch <= 65536 or args.fed < 1 or args.posterior_width < 1:
        raise ValueError("--steps must be at least 0, --batch from 1 to 65536, --fed and --posterior-width at least 1")
    if not (math.isfinite(args.lr) and args.lr > 0 and math.isfinite(args.beta) and args.beta >= 0
            and math.isfinite(args.mean_weight) and args.mean_weight >= 0):
        raise ValueError(f"--lr must be a finite number above 0, --beta and --mean-weight at least 0, got {args.lr}, "
                         f"{args.beta}, {args.mean_weight}")


def latent(args):
    check(args)
    train_sampler(args, LatentTrainer, CHECKPOINT_FORMAT)


def add_arguments(t):
    """`train.py latent`'s arguments."""
    t.add_argument("--weights", required=True, help="weight file to start from (its transition is trained further)")
    t.add_argument("--episodes", required=True, help="episodes to learn the futures from (failures too)")
    t.add_argument("--out", required=True, help="where to write the weights with the texture net")
    t.add_argument("--fed", type=int, default=19, help="fed-back sampled steps per window")
    t.add_argument("--width", type=int, default=256, help="units of the texture net's layer")
    t.add_argument("--posterior-width", type=int, default=256, help="units of the posterior's layer")
    t.add_argument("--lr", type=float, default=3e-4)
    t.add_argument("--beta", type=float, default=1.0, help="weight of the KL term (per code dimension)")
    t.add_argument("--mean-weight", type=float, default=0.0,
                   help="weight of the mean's own squared error (keeps the action's answer in the transition)")
    t.add_argument("--freeze-transition", action="store_true", help="train the texture net only")
    add_run_arguments(t)

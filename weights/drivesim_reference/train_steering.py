"""`train.py steering`: the transition's answer to the steering learnt from paired branches.

In every recorded drive the steering follows the road, so a transition can put down to the
steering what the road was doing anyway: the default's dream moved the road the wrong way a step
after the wheel turned and half as far as the real car after five (docs/judging.md). `python -m
drivesim branches` records the same state driven three ways (a constant -x, 0 and +x from a
point of a drive, the real frames of each); here the transition (`W V U b A a`; its texture net
and heads are kept) is fine-tuned on them. Each step draws --batch windows of the --episodes
(5 recorded codes, then --fed fed back: the mean path, the gradient through the whole window) and
--triplets points of the --branches (the three branches stepped alike from their 5 recorded
codes), and the loss is

    regular + --branch-weight * branches + --effect * effect

`regular` the squared error of the windows' predicted codes (with --distil: against what the
starting transition predicts for them, so that what the branches do not teach stays as it was
and the run needs none of the data the world learnt from), `branches` that of the branches'
codes, `effect` that of the difference between a point's +x and -x branches, predicted against
real: what the steering did, apart from what the road did. Adam (--lr), the gradient's norm
clipped to 1; --checkpoint resumes to the same bytes, as `train.py latent`.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn
from torch.nn import functional as F

from drivesim import episodes
from drivesim_reference.sequences import TEACHER, predict
from drivesim_reference.train_heads import encode_view, load_episodes
from drivesim_reference.train_texture import add_run_arguments, train_sampler

CHECKPOINT_FORMAT = "drivesim train.py steering checkpoint 1"
LEARNT = ("W", "V", "U", "b", "A", "a")


def triplets(model, path, cfg, no_mirror: bool):
    """The branches file's codes ``[points, 3, L, z]`` and actions ``[points, 3, L - 1, 2]`` (-x, 0,
    +x; every mirror image after the points as they are), or ValueError for a file that is not
    `python -m drivesim branches`' (its three branches a point, all as long, at least 6 frames)."""
    data = load_episodes(path, cfg, "branches", rewards=False)
    lengths = {int(e - s) for s, e in data.bounds()}
    if episodes.metadata(path).get("branches") != "3" or len(data) % 3 or len(lengths) != 1 \
            or min(lengths) < TEACHER + 1:
        raise ValueError(f"--branches {path}: not a file of `python -m drivesim branches` (three branches a point, "
                         f"each of {TEACHER} recorded frames and more): episode lengths {sorted(lengths)}")
    length = lengths.pop()
    codes, actions = [], []
    with torch.no_grad():
        for mirrored in (False,) if no_mirror else (False, True):
            z, c = encode_view(model, data, mirrored)
            codes.append(z.view(-1, 3, length, z.shape[1]))
            actions.append(c.view(-1, 3, length, c.shape[1])[:, :, :-1])
    return torch.cat(codes), torch.cat(actions)


def effect_error(predicted: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """The squared error of what the steering did: the difference between each point's +x and -x
    branches (index 2 and 0 of ``[points, 3, T, z]``), predicted against real."""
    return F.mse_loss(predicted[:, 2] - predicted[:, 0], real[:, 2] - real[:, 0])


class SteeringTrainer:
    """The transition fine-tuned on windows and paired branches (the module's loss)."""

    def __init__(self, model, cfg, args, device):
        self.model, self.args = model, args
        self.texture = getattr(model.transition, "texture", None)  # kept as it is
        codes, actions = triplets(model, args.branches, cfg, args.no_mirror)
        self.codes, self.actions = codes.to(device), actions.to(device)
        self.teacher = copy.deepcopy(model.transition) if args.distil else None
        self.learnt = [getattr(model.transition, name) for name in LEARNT]
        for tensor in self.learnt:
            tensor.requires_grad_(True)
        self.opt = torch.optim.Adam(self.learnt, lr=args.lr)

    def modules(self):
        return dict(transition=self.model.transition, opt=self.opt)

    def losses(self, z, c):
        """(regular, branches, effect) on windows ``z`` [B, T, z], ``c`` [B, T-1, 2] and
        --triplets points drawn from the branches."""
        tr = self.model.transition
        if self.teacher is not None:
            with torch.no_grad():
                target = predict(self.teacher, z, c, TEACHER)
        else:
            target = z[:, 1:]
        regular = F.mse_loss(predict(tr, z, c, TEACHER, detach=False), target)
        pick = torch.randint(len(self.codes), (self.args.triplets,), device=self.codes.device)
        zb, cb = self.codes[pick], self.actions[pick]
        length = zb.shape[2]
        predicted = predict(tr, zb.flatten(0, 1), cb.flatten(0, 1), TEACHER, detach=False)
        predicted = predicted.view(len(pick), 3, length - 1, -1)
        return regular, F.mse_loss(predicted, zb[:, :, 1:]), effect_error(predicted, zb[:, :, 1:])

    def step(self, z, c) -> dict:
        regular, branches, effect = self.losses(z, c)
        loss = regular + self.args.branch_weight * branches + self.args.effect * effect
        self.opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.learnt, 1.0)
        self.opt.step()
        return dict(regular=float(regular.detach()), branches=float(branches.detach()), effect=float(effect.detach()))


def check(args):
    if args.steps < 0 or not 1 <= args.batch <= 65536 or args.fed < 1 or not 1 <= args.triplets <= 65536:
        raise ValueError("--steps must be at least 0, --batch and --triplets from 1 to 65536, --fed at least 1")
    weights = (args.lr, args.effect, args.branch_weight)
    if not all(math.isfinite(w) for w in weights) or args.lr <= 0 or min(weights[1:]) < 0:
        raise ValueError(f"--lr must be a finite number above 0, --effect and --branch-weight finite and at least 0, "
                         f"got {args.lr}, {args.effect}, {args.branch_weight}")


def steering(args):
    check(args)
    train_sampler(args, SteeringTrainer, CHECKPOINT_FORMAT)


def add_arguments(t):
    """`train.py steering`'s arguments."""
    t.add_argument("--weights", required=True, help="weight file to start from (its transition is trained further)")
    t.add_argument("--episodes", required=True, help="episodes whose windows keep the rest of what it knows")
    t.add_argument("--branches", required=True, help="paired branches (python -m drivesim branches)")
    t.add_argument("--out", required=True, help="where to write the weights")
    t.add_argument("--fed", type=int, default=19, help="fed-back steps per window of the episodes")
    t.add_argument("--triplets", type=int, default=16, help="branch points per step (three branches each)")
    t.add_argument("--lr", type=float, default=1e-4)
    t.add_argument("--effect", type=float, default=1.0, help="weight of the steering's effect's squared error")
    t.add_argument("--branch-weight", type=float, default=1.0, help="weight of the branches' own squared error")
    t.add_argument("--distil", action="store_true",
                   help="the episodes' targets: the starting transition's predictions, not the recorded codes")
    add_run_arguments(t)

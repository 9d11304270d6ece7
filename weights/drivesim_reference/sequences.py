"""The transition stage: the tanh RNN trained on encoded 15-frame sequences, 5 frames teacher
forced, then 10 with its own output fed back, gradient stopped (the paper)."""

import json
import time

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from drivesim_reference.checkpoints import restore_random
from drivesim_reference.distributed import average_gradients, share
from drivesim_reference.vae_gan import to_input

SEQ, TEACHER = 15, 5  # transition sequences: 15 frames, the first 5 from the encoder


@torch.no_grad()
def encode(model, frames, batch=512):
    return torch.cat([model.encoder(to_input(frames[i:i + batch]))[0] for i in range(0, len(frames), batch)])


def predict(transition, z, c, teacher, detach=True, hidden=False, temperature=0.0, generator=None):
    """Run the transition over z [B,T,z] and c [B,T-1,a]: the first `teacher` inputs are the
    true codes, later ones the model's previous output, detached (the paper) or not (full
    back-propagation through time). Returns codes 1..T-1 (and, with `hidden`, the hidden
    state each step left, [B,T-1,hd]). With a temperature above 0 (a transition with the spread
    head), each output is a sample, `mean + temperature * exp(S h' + s) * noise`, as the crate's
    sampled rollouts draw them (the noise from `generator`, not the crate's; correlated by
    `transition.L` where the transition has it); with the texture net,
    `mean + texture(temperature * noise, h')` instead."""
    h = z.new_zeros(len(z), transition.W.shape[0])
    out, hs = [], []
    for t in range(z.shape[1] - 1):
        if t < teacher:
            zin = z[:, t]
        zin, h = transition(zin, h, c[:, t])
        if temperature > 0:
            noise = torch.randn(zin.shape, generator=generator, dtype=zin.dtype, device=zin.device)
            if hasattr(transition, "texture"):
                zin = zin + transition.texture(temperature * noise, h)
            else:
                if transition.correlated:
                    noise = noise @ transition.L.T
                zin = zin + temperature * transition.log_sigma(h).clamp(-20, 20).exp() * noise
        out.append(zin)
        hs.append(h)
        if detach:
            zin = zin.detach()  # no gradient through fed-back outputs
    return (torch.stack(out, 1), torch.stack(hs, 1)) if hidden else torch.stack(out, 1)


@torch.no_grad()
def noise_factor(transition, drives):
    """`transition.L`: the lower-triangular Cholesky factor of the correlation of the
    transition's standardised one-step errors on `drives` (pairs of codes [T, z] and actions
    [T-1 or T, a], raw), as the crate's `train::fit_noise_factor` fits it: along each drive
    from a zero state on the true codes, each error divided by the spread the head predicts,
    `(z - mean) / exp(S h' + s)`; their population covariance in float64, scaled to unit
    diagonal (a dimension without variance uncorrelated)."""
    zd = transition.A.shape[0]
    sums = torch.zeros(zd, dtype=torch.float64)
    products = torch.zeros(zd, zd, dtype=torch.float64)
    steps = 0
    for codes, actions in drives:
        codes, actions = codes.float().cpu(), actions.float().cpu()
        h = codes.new_zeros(transition.W.shape[0])
        errors = []
        for t in range(len(codes) - 1):
            mean, h = transition(codes[t], h, actions[t])
            errors.append((codes[t + 1] - mean) / transition.log_sigma(h).clamp(-20, 20).exp())
        if errors:
            e = torch.stack(errors).double()
            sums += e.sum(0)
            products += e.T @ e
            steps += len(e)
    if steps <= zd:
        raise ValueError(f"the noise's correlation needs more one-step errors than the code's {zd} dimensions: "
                         f"the drives hold {steps}")
    mean = sums / steps
    return _unit_diagonal_factor(products / steps - torch.outer(mean, mean))


def _unit_diagonal_factor(m: torch.Tensor) -> torch.Tensor:
    """The Cholesky factor (float32) of the symmetric float64 `m` scaled to unit diagonal (a
    dimension without variance uncorrelated), as the crate's `unit_diagonal` then `cholesky`."""
    std = m.diagonal().clamp_min(0).sqrt()
    scale = torch.outer(std, std)
    corr = torch.where(scale > 1e-12, m / scale.clamp_min(1e-300), torch.zeros_like(m))
    corr.fill_diagonal_(1.0)
    return torch.linalg.cholesky(corr).float()


def sharpen_noise(factor: torch.Tensor, power: int) -> torch.Tensor:
    """`transition.L` sharpened, as the crate's `train::sharpen_noise_factor`: the Cholesky
    factor of the correlation `L Lᵀ` raised to `power` (an integer, at least 1) and scaled back
    to unit diagonal, in float64; each dimension's spread stays the head's and the noise
    gathers where the one-step errors move together most (docs/history/next_second.md)."""
    if int(power) != power or power < 1:
        raise ValueError(f"the noise factor's power must be an integer at least 1, got {power}")
    factor = factor.double().cpu()
    if factor.ndim != 2 or factor.shape[0] != factor.shape[1] or not torch.isfinite(factor).all():
        raise ValueError(f"the noise factor must be a finite square matrix, got shape {tuple(factor.shape)}")
    if power == 1:
        return factor.float()
    return _unit_diagonal_factor(torch.linalg.matrix_power(factor @ factor.T, int(power)))


def spread_loss(transition, hidden, pred, target, teacher):
    """The spread head's loss: the Gaussian negative log-likelihood (without its constant) of
    each target dimension around the prediction, `0.5 r^2 exp(-2 l) + l` with `r` the
    prediction's error and `l = S h' + s`, mean over the windows, dimensions and the first
    `teacher` predictions: those from true codes, whose error is one step's innovation (a
    sampled rollout adds it at every step; the later predictions' error is the drift of the
    mean fed back, which it would add again and again). The mean and the hidden states are
    detached: the head learns the error the mean makes, and the mean trains as without it."""
    steps = min(teacher, pred.shape[1])
    log_sigma = transition.log_sigma(hidden[:, :steps].detach())
    r = target[:, :steps] - pred[:, :steps].detach()
    return (0.5 * r.square() * torch.exp(-2 * log_sigma) + log_sigma).mean()


def transition_step(tr, opt, z, c, teacher, clip, detach=True):
    """One training step of the transition `tr` on windows z [B,T,z], c [B,T-1,a]: MSE of
    the predictions (plus the spread head's `spread_loss` where `tr` has one), backward, the
    mean's gradient norm clipped to `clip` (the head's gradient is not: it is a loss of its
    own, and Adam bounds its steps), `opt.step()`. Returns the loss and the gradients as
    computed (before clipping), by parameter name."""
    pred, hidden = predict(tr, z, c, teacher, detach, hidden=True)
    loss = F.mse_loss(pred, z[:, 1:])
    if tr.spread:
        loss = loss + spread_loss(tr, hidden, pred, z[:, 1:], teacher)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    average_gradients([p.grad for p in tr.parameters()])
    grads = {name: p.grad.detach().clone() for name, p in tr.named_parameters()}
    nn.utils.clip_grad_norm_([p for name, p in tr.named_parameters() if name not in ("S", "s")], clip)
    opt.step()
    return loss.detach(), grads


def train_transition(model, dis, codes, actions, starts, args, log, checkpoints, state=None):
    """Trains the transition for --transition-steps on windows of the encoded episodes, from
    the checkpoint `state` where it is one of this stage; then folds the action normalisation
    into U and b and returns it."""
    dev = codes.device
    mean, std = actions.mean(0), actions.std(0).clamp_min(1e-6)
    norm = (actions - mean) / std
    tr = model.transition
    opt = torch.optim.Adam(tr.parameters(), lr=args.transition_lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.transition_steps)
    rng = np.random.default_rng(args.seed)
    done = 0
    if state is not None and state["step"]:
        opt.load_state_dict(state["optimisers"][0])
        sched.load_state_dict(state["scheduler"])
        restore_random(state, windows=rng)
        done = state["step"]
    offsets = torch.arange(SEQ, device=dev)
    start = time.time()
    for step in range(done + 1, args.transition_steps + 1):
        idx = share(torch.as_tensor(rng.choice(starts, args.transition_batch), device=dev)[:, None] + offsets)
        z, c = codes[idx], norm[idx[:, :-1]]
        loss, _ = transition_step(tr, opt, z, c, TEACHER, 1.0)
        sched.step()
        if step % args.log_every == 0 or step == args.transition_steps:
            entry = dict(phase="transition", step=step, seconds=round(time.time() - start, 1), mse=loss.item())
            log.append(entry)
            print(json.dumps(entry), flush=True)
        if checkpoints.due(step, args.transition_steps):
            checkpoints.save("transition", step, model, dis, log, [opt], sched, windows=rng)
    # U c_norm + b = (U / std) c + (b - U mean / std): the exported model takes raw actions.
    with torch.no_grad():
        tr.U /= std
        tr.b -= tr.U @ mean
    return dict(action_mean=mean.tolist(), action_std=std.tolist())

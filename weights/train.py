"""Train the drivesim networks as in the paper, and evaluate a weight file.

  weights/tool train fit --data train.safetensors.gz --out default.safetensors [--device cuda]
  weights/tool train eval --weights default.safetensors --data eval.safetensors.gz --figures figures/
  weights/tool train step --stage transition|vae-gan --weights W.safetensors --batch B.safetensors --out O.safetensors

fit: (1) VAE-GAN (Larsen et al.): encoder, generator and a discriminator. The encoder
minimises the KL prior plus the reconstruction error, measured on the discriminator's 3rd
conv features and in pixels; the generator minimises the same reconstruction error and
fools the discriminator with both reconstructions and prior samples; the GAN gradient never
reaches the encoder. (2) The transition RNN on encoded 15-frame sequences: 5 frames teacher
forced, then 10 with its own output fed back, gradient stopped. Adam throughout. The action
normalisation used in training is folded into U and b, so the exported model takes raw
(speed, steering). Writes the f16 drivesim file and a JSON log beside it.

step: one training step of a stage on a given batch, writing the losses, the gradients (for the
transition, before clipping) and the updated tensors: the reference of the Rust `train step`
(weights/README.md). The VAE-GAN step reads the discriminator from the weight file, where `fit`
stores it (`discriminator.*`), so training can resume from either side.

eval: reconstruction PSNR, 1-step and 10-step latent prediction error, steering response,
a contact sheet of a 100-step rollout, all from frames the model never saw; and the fidelity
figures (`fidelity` in eval.json, weights/README.md §5): PSNR percentiles, the latent error
after 10 and 30 fed-back steps against the mean code, the road's direction under constant
steering, the fed-back codes' norm.
"""

import argparse
import contextlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image
import torch.distributed as dist
import torch.distributed.nn.functional as dist_nn
from torch import nn
from torch.nn import functional as F

import episodes
from model import LEAK, Config, DriveSim, _conv, load_discriminator, load_drivesim, save_drivesim
import package

_files = package.load("_files.py")

SEQ, TEACHER = 15, 5  # transition sequences: 15 frames, the first 5 from the encoder
STEER = 0.6  # constant steering of the steering-response test, well inside the recorded range


# ---------------------------------------------------------------- several processes

def world() -> int:
    """Processes training together: torchrun's WORLD_SIZE once `start_distributed` ran, else 1."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def start_distributed(device: str) -> tuple[int, torch.device]:
    """Under torchrun (WORLD_SIZE set): joins the process group (NCCL on GPUs, gloo on the CPU)
    and returns this process's rank and device; otherwise rank 0 and `device`."""
    if "WORLD_SIZE" not in os.environ:
        return 0, torch.device(device)
    dev = torch.device(device)
    if dev.type == "cuda":
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        torch.cuda.set_device(dev)
    dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    return dist.get_rank(), dev


def average_gradients(grads):
    """The mean over the processes of each process's gradients, in place (each process's loss is
    the mean over its equal share of the global batch, so this is the global batch's gradient)."""
    if world() > 1:
        for g in grads:
            dist.all_reduce(g)
            g /= world()


def share(t: torch.Tensor) -> torch.Tensor:
    """This process's equal share of a global batch (all of it in a single process)."""
    if world() == 1:
        return t
    if len(t) % world():
        raise ValueError(f"a batch of {len(t)} does not split over {world()} processes")
    n = len(t) // world()
    return t[dist.get_rank() * n:(dist.get_rank() + 1) * n]


def global_var(t: torch.Tensor) -> torch.Tensor:
    """The unbiased variance of every value of `t` on every process (no gradient needed)."""
    if world() == 1:
        return t.var()
    stats = torch.stack([t.sum(), t.square().sum(), torch.tensor(float(t.numel()), device=t.device, dtype=t.dtype)])
    dist.all_reduce(stats)
    total, squares, n = stats
    return (squares - total * total / n) / (n - 1)


class GlobalBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are those of the global batch, over every process
    (differentiably, through `all_reduce`), so that a run on several processes trains as one
    process with the global batch would. Runs on the CPU's gloo too (nn.SyncBatchNorm needs
    GPUs). In one process, or in eval mode, it is BatchNorm2d; same tensors, same names."""

    def forward(self, x):
        if not (self.training and world() > 1):
            return super().forward(x)
        count = torch.tensor(float(x.numel() // x.shape[1]), device=x.device, dtype=x.dtype)
        dist.all_reduce(count)
        sums = dist_nn.all_reduce(torch.stack([x.sum((0, 2, 3)), x.square().sum((0, 2, 3))]))
        mean = sums[0] / count
        var = sums[1] / count - mean.square()
        with torch.no_grad():
            m = self.momentum
            self.running_mean.mul_(1 - m).add_(m * mean)
            self.running_var.mul_(1 - m).add_(m * var * count / (count - 1))
            self.num_batches_tracked += 1
        shape = (1, -1, 1, 1)
        scale = self.weight * torch.rsqrt(var + self.eps)
        return (x - mean.view(shape)) * scale.view(shape) + self.bias.view(shape)


def globalise_batch_norms(module: nn.Module) -> nn.Module:
    """Every BatchNorm2d of `module` as a GlobalBatchNorm holding the same tensors."""
    for name, child in module.named_children():
        if type(child) is nn.BatchNorm2d:
            g = GlobalBatchNorm(child.num_features, child.eps, child.momentum).to(child.weight.device)
            g.load_state_dict(child.state_dict())
            setattr(module, name, g)
        else:
            globalise_batch_norms(child)
    return module


# ---------------------------------------------------------------- training

class Discriminator(nn.Module):
    """Mirror of the encoder: 4 strided convs (BN on all but the first) and a logit.
    Also returns the 3rd conv's output before BN, the features of the reconstruction loss."""

    def __init__(self, cfg):
        super().__init__()
        chans = [cfg.channels] + [cfg.base_channels * 2**i for i in range(cfg.layers)]
        self.convs = nn.ModuleList(_conv(cfg, a, b) for a, b in zip(chans, chans[1:]))
        self.bns = nn.ModuleList(nn.BatchNorm2d(c) if i else nn.Identity() for i, c in enumerate(chans[1:]))
        self.out = nn.Linear(cfg.flat, 1)

    def forward(self, x):
        for i, (conv, bn) in enumerate(zip(self.convs, self.bns)):
            x = conv(x)
            if i == 2:
                features = x
            x = F.leaky_relu(bn(x), LEAK)
        return self.out(x.flatten(1)).squeeze(1), features


@contextlib.contextmanager
def frozen_bn_stats(module):
    """Batch-norm layers normalise with batch statistics but leave their running averages
    alone. Prior samples go through the generator this way, so the running statistics
    exported for inference describe encoder codes only."""
    bns = [m for m in module.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    saved = [m.momentum for m in bns]
    for m in bns:
        m.momentum = 0.0
    try:
        yield
    finally:
        for m, mom in zip(bns, saved):
            m.momentum = mom


def to_input(frames_u8):
    """uint8 NHWC -> float NCHW in [-1, 1]."""
    return frames_u8.permute(0, 3, 1, 2).float() / 127.5 - 1.0


def to_image(x):
    """float NCHW in [-1, 1] -> uint8 NHWC numpy."""
    return ((x.clamp(-1, 1) + 1) * 127.5).round().byte().permute(0, 2, 3, 1).cpu().numpy()


def kl_prior(mu, logsigma):
    """KL(N(mu, sigma) || N(0, 1)), mean over batch and code dimensions."""
    return 0.5 * (mu.square() + torch.exp(2 * logsigma) - 1 - 2 * logsigma).mean()


def bce(logits, real):
    return F.binary_cross_entropy_with_logits(logits, torch.full_like(logits, float(real)))


# The loss weights of the VAE-GAN (the `fit` defaults): KL prior, discriminator features,
# pixel L1, and the generator's GAN term.
LOSS_WEIGHTS = dict(kl=1e-3, feature=0.1, pixel=1.0, gan=0.01)
ADAM_VAE_GAN = dict(lr=2e-4, betas=(0.5, 0.999))


def wide(t):
    """The losses' precision: float32 for autocast's bfloat16, float64 kept (the fixtures'
    reference runs the step in float64 too)."""
    return t if t.dtype == torch.float64 else t.float()


def vae_gan_step(enc, gen, dis, opts, x, eps, prior, w=LOSS_WEIGHTS, amp=contextlib.nullcontext()):
    """One VAE-GAN step on frames x [B,C,H,W] with the reparametrisation draws eps [B,z] and
    prior samples prior [B,z]: the discriminator's step, then the encoder's and generator's
    (`opts` = their Adam optimisers, in the order encoder, generator, discriminator). Returns
    the losses and the gradients as computed, by module: the Rust `train step`'s reference."""
    opt_e, opt_g, opt_d = opts
    with amp:
        mu, logsigma = enc(x)
        xr = gen(mu + eps * logsigma.exp())  # reparametrisation trick
        with frozen_bn_stats(gen):
            xp = gen(prior)

        # Discriminator: real frames against reconstructions and prior samples.
        d_real, _ = dis(x)
        d_fake, _ = dis(torch.cat([xr, xp]).detach())
        loss_d = bce(d_real, 1) + bce(d_fake, 0)
    opt_d.zero_grad(set_to_none=True)
    loss_d.backward()
    average_gradients([p.grad for p in dis.parameters()])
    grads_d = [p.grad.detach().clone() for p in dis.parameters()]
    opt_d.step()

    # Encoder and generator; the discriminator is a fixed cost function here.
    with amp:
        with torch.no_grad():
            _, f_real = dis(x)
        d_gen, f_gen = dis(torch.cat([xr, xp]))
        f_rec = f_gen[: len(x)]
        # Feature error relative to the features' spread: its scale stays fixed while
        # the discriminator's features grow or shrink.
        f_rec, f_real, xr_, mu, logsigma, d_gen = map(wide, (f_rec, f_real, xr, mu, logsigma, d_gen))
        llike = (f_rec - f_real).square().mean() / global_var(f_real).clamp_min(1e-6)
        pixel = (xr_ - x).abs().mean()
        kl = kl_prior(mu, logsigma)
        gan = bce(d_gen, 1)
    recon = w["feature"] * llike + w["pixel"] * pixel
    loss_e = w["kl"] * kl + recon
    loss_g = recon + w["gan"] * gan  # only the generator sees the GAN term
    grads_e = torch.autograd.grad(loss_e, list(enc.parameters()), retain_graph=True)
    grads_g = torch.autograd.grad(loss_g, list(gen.parameters()))
    average_gradients(list(grads_e) + list(grads_g))
    for params, grads, opt in ((enc.parameters(), grads_e, opt_e), (gen.parameters(), grads_g, opt_g)):
        for p, g in zip(params, grads):
            p.grad = g
        opt.step()
    losses = dict(d=loss_d.detach(), e=loss_e.detach(), g=loss_g.detach(), gan=gan.detach(),
                  feature=llike.detach(), pixel_l1=pixel.detach(), kl=kl.detach())
    grads = dict(encoder=grads_e, generator=grads_g, discriminator=grads_d)
    return losses, grads, xr.detach()


def train_vae_gan(model, frames, args, log):
    dev = frames.device
    enc, gen = model.encoder, model.generator
    dis = globalise_batch_norms(Discriminator(model.cfg).to(dev))
    adam = dict(ADAM_VAE_GAN, lr=args.lr)
    opts = [torch.optim.Adam(m.parameters(), **adam) for m in (enc, gen, dis)]
    amp = torch.autocast("cuda", torch.bfloat16) if dev.type == "cuda" else contextlib.nullcontext()
    weights = dict(kl=args.w_kl, feature=args.w_feature, pixel=args.w_pixel, gan=args.w_gan)
    gen_rng = torch.Generator(dev).manual_seed(args.seed)
    model.train()
    start, deadline = time.time(), time.time() + 60 * args.max_minutes
    for step in range(1, args.vae_steps + 1):
        # Every process draws the global batch and takes its share: the same run on any number.
        idx = torch.randint(len(frames), (args.batch,), device=dev, generator=gen_rng)
        x = to_input(frames[share(idx)])
        shape = (args.batch, model.cfg.z_dim)
        eps, prior = share(torch.randn(shape, device=dev)), share(torch.randn(shape, device=dev))
        losses, _, xr = vae_gan_step(enc, gen, dis, opts, x, eps, prior, weights, amp)

        if step % args.log_every == 0 or step == args.vae_steps:
            entry = dict(phase="vae_gan", step=step, seconds=round(time.time() - start, 1),
                         d=losses["d"].item(), gan=losses["gan"].item(), feature=losses["feature"].item(),
                         pixel_l1=losses["pixel_l1"].item(), kl=losses["kl"].item(), psnr_batch=psnr(xr.float(), x))
            log.append(entry)
            print(json.dumps(entry), flush=True)
        late = torch.tensor(float(time.time() > deadline), device=dev)
        if world() > 1:
            dist.all_reduce(late, op=dist.ReduceOp.MAX)  # the processes stop together
        if late.item():
            log.append(dict(phase="vae_gan", stopped_early_at=step, reason="--max-minutes"))
            print(f"VAE-GAN stopped at step {step}: --max-minutes reached", flush=True)
            break
    model.eval()
    return dis.eval()


def psnr(x, y):
    """Mean PSNR in dB of frames in [-1, 1], on the 0-255 scale."""
    mse = ((x.clamp(-1, 1) - y) * 127.5).square().flatten(1).mean(1)
    return float((10 * torch.log10(255.0**2 / mse.clamp_min(1e-10))).mean())


@torch.no_grad()
def encode(model, frames, batch=512):
    return torch.cat([model.encoder(to_input(frames[i:i + batch]))[0] for i in range(0, len(frames), batch)])


def windows(data, length):
    """Start indices of every run of `length` frames inside one episode."""
    return np.concatenate([np.arange(s, e - length + 1) for s, e in data.bounds() if e - s >= length])


def predict(transition, z, c, teacher, detach=True):
    """Run the transition over z [B,T,z] and c [B,T-1,a]: the first `teacher` inputs are the
    true codes, later ones the model's previous output, detached (the paper) or not (full
    back-propagation through time). Returns codes 1..T-1."""
    h = z.new_zeros(len(z), transition.W.shape[0])
    out = []
    for t in range(z.shape[1] - 1):
        if t < teacher:
            zin = z[:, t]
        zin, h = transition(zin, h, c[:, t])
        out.append(zin)
        if detach:
            zin = zin.detach()  # no gradient through fed-back outputs
    return torch.stack(out, 1)


def transition_step(tr, opt, z, c, teacher, clip, detach=True):
    """One training step of the transition `tr` on windows z [B,T,z], c [B,T-1,a]: MSE of
    the predictions, backward, gradient norm clipped to `clip`, `opt.step()`. Returns the loss
    and the gradients as computed (before clipping), by parameter name."""
    loss = F.mse_loss(predict(tr, z, c, teacher, detach), z[:, 1:])
    opt.zero_grad(set_to_none=True)
    loss.backward()
    average_gradients([p.grad for p in tr.parameters()])
    grads = {name: p.grad.detach().clone() for name, p in tr.named_parameters()}
    nn.utils.clip_grad_norm_(tr.parameters(), clip)
    opt.step()
    return loss.detach(), grads


def train_transition(model, codes, actions, starts, args, log):
    dev = codes.device
    mean, std = actions.mean(0), actions.std(0).clamp_min(1e-6)
    norm = (actions - mean) / std
    tr = model.transition
    opt = torch.optim.Adam(tr.parameters(), lr=args.transition_lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.transition_steps)
    rng = np.random.default_rng(args.seed)
    offsets = torch.arange(SEQ, device=dev)
    start = time.time()
    for step in range(1, args.transition_steps + 1):
        idx = share(torch.as_tensor(rng.choice(starts, args.transition_batch), device=dev)[:, None] + offsets)
        z, c = codes[idx], norm[idx[:, :-1]]
        loss, _ = transition_step(tr, opt, z, c, TEACHER, 1.0)
        sched.step()
        if step % args.log_every == 0 or step == args.transition_steps:
            entry = dict(phase="transition", step=step, seconds=round(time.time() - start, 1), mse=loss.item())
            log.append(entry)
            print(json.dumps(entry), flush=True)
    # U c_norm + b = (U / std) c + (b - U mean / std): the exported model takes raw actions.
    with torch.no_grad():
        tr.U /= std
        tr.b -= tr.U @ mean
    return dict(action_mean=mean.tolist(), action_std=std.tolist())


def fit(args):
    rank, dev = start_distributed(args.device)
    if rank:  # one process reports
        sys.stdout = open(os.devnull, "w")
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    data = episodes.read(args.data)
    cfg = Config(height=data.frames.shape[1], width=data.frames.shape[2], channels=3,
                 base_channels=args.base_channels, z_dim=args.z_dim, hidden_dim=args.hidden_dim, action_dim=2)
    frames = torch.from_numpy(data.frames).to(dev)
    print(f"{len(data)} episodes, {len(frames)} frames, config {cfg}", flush=True)
    model = globalise_batch_norms(DriveSim(cfg).to(dev))
    log = [dict(args={k: str(v) for k, v in vars(args).items()}, config=json.loads(cfg.to_json()),
                episodes=len(data), frames=len(frames))]
    t0 = time.time()
    dis = train_vae_gan(model, frames, args, log)
    t1 = time.time()
    codes = encode(model, frames)
    actions = torch.from_numpy(data.actions).to(dev)
    norm = train_transition(model, codes, actions, windows(data, SEQ), args, log)
    t2 = time.time()
    log.append(dict(vae_gan_seconds=round(t1 - t0, 1), transition_seconds=round(t2 - t1, 1), **norm))
    if rank:  # every process holds the same weights: the first writes them
        dist.destroy_process_group()
        return
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # What the actions mean travels with the weights (units as the episodes file recorded them).
    low, high = actions.min(0).values.tolist(), actions.max(0).values.tolist()
    described = [dict(name=name, unit="as recorded", mean=m, std=sd, min=lo, max=hi) for name, m, sd, lo, hi
                 in zip(("speed", "steering"), norm["action_mean"], norm["action_std"], low, high)]
    hz = episodes.metadata(args.data).get("frame_hz")
    save_drivesim(model.cpu(), cfg, out, args.dtype, actions=described, discriminator=dis.cpu(),
                  frame_hz=float(hz) if hz else None)
    with _files.atomic_write(out.with_suffix(".log.json")) as f:
        f.write(json.dumps(log, indent=1).encode())
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB) in {t2 - t0:.0f} s", flush=True)
    if world() > 1:
        dist.destroy_process_group()


# ---------------------------------------------------------------- evaluation

def sheet(rows, gap=2):
    """Grid of uint8 HWC frames (a list of rows of frames) on a white background."""
    h, w, _ = rows[0][0].shape
    cols = max(len(r) for r in rows)
    out = np.full((len(rows) * (h + gap) - gap, cols * (w + gap) - gap, 3), 255, np.uint8)
    for i, row in enumerate(rows):
        for j, f in enumerate(row):
            out[i * (h + gap):i * (h + gap) + h, j * (w + gap):j * (w + gap) + w] = f
    return Image.fromarray(out)


@torch.no_grad()
def rollout(model, seed_codes, actions):
    """Codes of the frames after the seeds: seed_codes [S,z], actions [S-1+T,2] -> [T,z].
    Batched twin of DriveSim.rollout that starts from codes."""
    z = torch.cat([seed_codes, seed_codes.new_zeros(len(actions) + 1 - len(seed_codes), seed_codes.shape[1])])
    return predict(model.transition, z[None], actions[None], len(seed_codes))[0, len(seed_codes) - 1:]


def road_offset(frame):
    """The road's centre in a band just ahead of the car minus the car's column, in pixels, or
    None where no road shows (grey pixels against grass, as examples/drive.rs measures it)."""
    h, w, _ = frame.shape
    band = frame[h * 6 // 10:h * 3 // 4].astype(np.int16)
    lo, hi = band.min(2), band.max(2)
    grey = (hi - lo < 25) & (hi < 170) & (hi > 60)
    xs = np.nonzero(grey)[1]
    return float(xs.mean() - w // 2) if len(xs) else None


def mean_offset(frames):
    """The mean of `road_offset` over the frames that show road, or None if none does."""
    seen = [o for o in map(road_offset, frames) if o is not None]
    return float(np.mean(seen)) if seen else None


FED_BACK = (10, 30)  # fed-back steps at which the latent error is reported
DIRECTION_SEEDS, DIRECTION_STEPS, DIRECTION_STEER = 50, 30, (0.3, 0.6)


@torch.no_grad()
def fidelity(model, data, codes, recon, frames, actions, decode):
    """The fidelity figures of issue 19 on held-out episodes: reconstruction PSNR (mean and 10th
    percentile over frames); the latent error after 10 and 30 fed-back steps (and over all of the
    first 10 and 30) against predicting the data's mean code; how often the road sits further left
    under constant right steering than under left (road centre in the band ahead, 30 steps, 50
    starts); and the norm of rolled-out codes against encoded frames. The road's offset is averaged
    over every 3rd generated frame that shows road (a road the car turns away from leaves the
    band)."""
    per_frame = ((recon.clamp(-1, 1) - to_input(frames)) * 127.5).square().flatten(1).mean(1)
    per_frame = 10 * torch.log10(255.0**2 / per_frame.clamp_min(1e-10))
    out = dict(psnr_db=float(per_frame.mean()), psnr_p10_db=float(per_frame.quantile(0.1)))

    horizon = max(FED_BACK)
    starts = windows(data, TEACHER + horizon)
    if len(starts):
        starts = starts[::5]
        idx = torch.as_tensor(starts)[:, None] + torch.arange(TEACHER + horizon)
        z, c = codes[idx], actions[idx[:, :-1]]
        pred = predict(model.transition, z, c, TEACHER)  # pred[:, t]: the code of frame t+1
        mean_code = codes.mean(0)
        latent = dict(windows=len(starts))
        for k in FED_BACK:
            t = TEACHER - 1 + k  # the k-th fed-back prediction
            # After the k-th fed-back step, and (the other reading of "after k steps") over all
            # of the first k.
            readings = ((k, pred[:, t - 1], z[:, t]), (f"1_to_{k}", pred[:, TEACHER - 1:t], z[:, TEACHER:t + 1]))
            for name, p, true in readings:
                err, base = float((p - true).square().mean()), float((mean_code - true).square().mean())
                latent[f"mse_{name}"], latent[f"mean_code_mse_{name}"], latent[f"ratio_{name}"] = err, base, err / base
        out["latent"] = latent
        fed = pred[:, TEACHER - 1:]
        out["code_norm"] = dict(rollout=float(fed.norm(dim=2).mean()), encoded=float(codes.norm(dim=1).mean()))
        out["code_norm"]["ratio"] = out["code_norm"]["rollout"] / out["code_norm"]["encoded"]

    starts = windows(data, TEACHER)
    if len(starts):
        picks = starts[np.linspace(0, len(starts) - 1, DIRECTION_SEEDS).astype(int)]
        seeds = codes[torch.as_tensor(picks)[:, None] + torch.arange(TEACHER)]
        speed = actions[torch.as_tensor(picks) + TEACHER - 1, 0]
        direction = {}
        for steer in DIRECTION_STEER:
            offsets = {}
            for sign in (-1, 1):
                c = torch.stack([speed, torch.full_like(speed, sign * steer)], 1)[:, None]
                c = c.expand(-1, TEACHER - 1 + DIRECTION_STEPS, -1)
                z = torch.cat([seeds, seeds.new_zeros(len(seeds), DIRECTION_STEPS, seeds.shape[2])], 1)
                # Every 3rd step: a road that turns out of the band late still counts its way.
                fed = predict(model.transition, z, c, TEACHER)[:, TEACHER - 1 + 2::3]
                frames_of = decode(fed.flatten(0, 1)).reshape(len(seeds), fed.shape[1], *frames.shape[1:])
                offsets[sign] = [mean_offset(rollout) for rollout in frames_of]
            # Steering right (positive) turns the car right: the road moves left in the image.
            right_way = [l is not None and r is not None and r < l for l, r in zip(offsets[-1], offsets[1])]
            direction[str(steer)] = float(np.mean(right_way))
        out["road_moves_right_way"] = direction
    return out


@torch.no_grad()
def evaluate(args):
    model, cfg = load_drivesim(args.weights)
    data = episodes.read(args.data)
    figs = Path(args.figures)
    figs.mkdir(parents=True, exist_ok=True)
    frames = torch.from_numpy(data.frames)
    actions = torch.from_numpy(data.actions)
    decode = lambda z: to_image(model.generator(z))  # noqa: E731
    result = dict(weights=str(args.weights), data=str(args.data), episodes=len(data), frames=len(frames))

    # Reconstruction: encoder mean -> generator.
    codes = encode(model, frames, 256)
    recon = torch.cat([model.generator(codes[i:i + 256]) for i in range(0, len(codes), 256)])
    result["reconstruction_psnr_db"] = psnr(recon, to_input(frames))
    pick = np.linspace(0, len(frames) - 1, 8).astype(int)
    sheet([list(data.frames[pick]), list(to_image(recon[pick]))]).save(figs / "reconstruction.png")

    # Latent prediction: 5 true codes, then 10 steps fed back, from windows 5 frames apart.
    starts = windows(data, SEQ)[::5]
    idx = torch.as_tensor(starts)[:, None] + torch.arange(SEQ)
    z, c = codes[idx], actions[idx[:, :-1]]
    pred = predict(model.transition, z, c, TEACHER)  # pred[:, t] is the code of frame t+1
    first, last = TEACHER - 1, SEQ - 2
    mse = lambda a, b: float((a - b).square().mean())  # noqa: E731
    result["latent"] = dict(
        windows=len(starts),
        mse_1_step=mse(pred[:, first], z[:, first + 1]),
        mse_10_step=mse(pred[:, last], z[:, last + 1]),
        copy_last_1_step=mse(z[:, first], z[:, first + 1]),  # baseline: nothing moves
        copy_last_10_step=mse(z[:, first], z[:, last + 1]),
        code_variance=float(codes.var(0).mean()),  # baseline: predict the mean code
    )

    result["fidelity"] = fidelity(model, data, codes, recon, frames, actions, decode)

    # Steering response: same seed frames, constant actions, 30 steps.
    s0, _ = data.bounds()[0]
    seed_codes = codes[s0:s0 + TEACHER]
    speed = float(actions[s0:s0 + 30, 0].mean())
    steps = 30

    def constant(steer):
        return rollout(model, seed_codes, torch.tensor([[speed, steer]]).repeat(TEACHER - 1 + steps, 1))

    left, right, left_again = constant(-STEER), constant(STEER), constant(-STEER)
    img = {k: decode(v).astype(np.float32) for k, v in (("l", left), ("r", right), ("l2", left_again))}
    result["steering"] = dict(
        speed=speed, steps=steps, steering=[-STEER, STEER],
        left_vs_right_pixel_mad=float(np.abs(img["l"] - img["r"]).mean()),
        left_vs_right_latent_mse=mse(left, right),
        identical_actions_pixel_mad=float(np.abs(img["l"] - img["l2"]).mean()),
        identical_actions_latent_mse=mse(left, left_again),
    )
    straight = decode(constant(0.0))
    every = list(range(2, steps, 3))
    rows = [img["l"][every].astype(np.uint8), straight[every], img["r"][every].astype(np.uint8)]
    sheet([list(row) for row in rows]).save(figs / "steering.png")  # left, straight, right

    # Contact sheet: 5 seed frames, then every 10th frame of a 100-step rollout driven by
    # the recorded actions; the row below shows the recorded frames at the same steps.
    n = 100
    if data.bounds()[0][1] - s0 >= TEACHER + n:
        pred = rollout(model, seed_codes, actions[s0:s0 + TEACHER - 1 + n])
        shown = list(range(9, n, 10))
        top = list(data.frames[s0:s0 + TEACHER]) + list(decode(pred[shown]))
        bottom = list(data.frames[s0:s0 + TEACHER]) + list(data.frames[[s0 + TEACHER + i for i in shown]])
        sheet([top, bottom]).save(figs / "contact_sheet.png")

    if args.seed_clip:
        clip = episodes.Episodes(data.frames[s0:s0 + 8].copy(), data.actions[s0:s0 + 8].copy(),
                                 np.zeros(1, dtype=np.int64))
        episodes.write(args.seed_clip, clip, {"source": f"first 8 frames of {args.data}"})
    (figs / "eval.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


def step(args):
    """`train step`: one training step of a stage on a batch file; see weights/README.md."""
    {"transition": step_transition, "vae-gan": step_vae_gan}[args.stage](args)


def step_vae_gan(args):
    """One VAE-GAN step (vae_gan_step) on `frames`, `eps` and `prior` from the batch file, with
    the discriminator stored in the weight file."""
    from safetensors.torch import load_file, save_file

    rank, _ = start_distributed("cpu")
    model, cfg = load_drivesim(args.weights)
    stored = load_discriminator(args.weights)
    if not stored:
        raise ValueError(f"{args.weights}: no discriminator.* tensors (the VAE-GAN step needs them)")
    dis = Discriminator(cfg)
    missing, unexpected = dis.load_state_dict(stored, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(f"{args.weights}: discriminator tensors missing {missing}, unexpected {unexpected}")
    batch = load_file(args.batch)
    for name in ("frames", "eps", "prior"):
        if name not in batch:
            raise ValueError(f"{args.batch}: needs a tensor `{name}`")
    frames, eps, prior = batch["frames"], batch["eps"], batch["prior"]
    want = [cfg.height, cfg.width, cfg.channels]
    if frames.dim() != 4 or list(frames.shape[1:]) != want or frames.shape[0] < 1:
        raise ValueError(f"`frames` has shape {list(frames.shape)}: expected [B >= 1, {', '.join(map(str, want))}]")
    if frames.dtype == torch.uint8:
        x = to_input(frames)
    elif frames.dtype == torch.float32:
        x = frames.permute(0, 3, 1, 2)
    else:
        raise ValueError(f"`frames` is {frames.dtype}: expected uint8 or float32 in [-1, 1]")
    for name, t in (("eps", eps), ("prior", prior)):
        if t.dtype != torch.float32 or list(t.shape) != [len(frames), cfg.z_dim]:
            raise ValueError(f"`{name}` is {t.dtype} {list(t.shape)}: expected float32 [{len(frames)}, {cfg.z_dim}]")
    globalise_batch_norms(model)
    globalise_batch_norms(dis)
    model.train()
    dis.train()
    # Under torchrun each process takes its share of the batch: the same step (gradients and
    # updated tensors within float tolerance) as one process on all of it.
    x, eps, prior = share(x), share(eps), share(prior)
    nets = dict(encoder=model.encoder, generator=model.generator, discriminator=dis)
    lr = 2e-4 if args.lr is None else args.lr
    opts = [torch.optim.Adam(m.parameters(), **dict(ADAM_VAE_GAN, lr=lr)) for m in nets.values()]
    losses, grads, _ = vae_gan_step(model.encoder, model.generator, dis, opts, x, eps, prior)
    if world() > 1:
        for v in losses.values():  # each process's share of the batch is equal
            dist.all_reduce(v)
            v /= world()
        dist.destroy_process_group()
        if rank:
            return
    out = {f"loss.{k}": v.reshape(1) for k, v in losses.items()}
    for net, module in nets.items():
        out.update({f"grad.{net}.{name}": g for (name, _), g in zip(module.named_parameters(), grads[net])})
        out.update({f"{net}.{k}": v for k, v in module.state_dict().items() if not k.endswith("num_batches_tracked")})
    save_file({k: v.float().contiguous() for k, v in out.items()}, args.out)
    print(", ".join(f"{k} {v.item():.6e}" for k, v in losses.items()) + f": wrote {args.out}")


def step_transition(args):
    """One transition step on `codes` and `actions` from the batch file."""
    from safetensors.torch import load_file, save_file

    model, cfg = load_drivesim(args.weights)
    tr = model.transition.float()
    batch = load_file(args.batch)
    for name in ("codes", "actions"):
        if name not in batch or batch[name].dtype != torch.float32:
            raise ValueError(f"{args.batch}: needs a float32 tensor `{name}`")
    z, c = batch["codes"], batch["actions"]
    if z.dim() != 3 or z.shape[0] < 1 or z.shape[1] < 2 or z.shape[2] != cfg.z_dim:
        raise ValueError(f"`codes` has shape {list(z.shape)}: expected [B >= 1, T >= 2, {cfg.z_dim}]")
    want = [z.shape[0], z.shape[1] - 1, cfg.action_dim]
    if list(c.shape) != want:
        raise ValueError(f"`actions` has shape {list(c.shape)}: expected {want}")
    if args.teacher < 1:
        raise ValueError("--teacher must be at least 1")
    opt = torch.optim.Adam(tr.parameters(), lr=1e-3 if args.lr is None else args.lr)
    loss, grads = transition_step(tr, opt, z, c, args.teacher, args.clip, detach=not args.full_bptt)
    out = {"loss": loss.reshape(1)}
    out.update({f"grad.transition.{k}": g for k, g in grads.items()})
    out.update({f"transition.{k}": p.detach().clone() for k, p in tr.named_parameters()})
    save_file({k: v.float().contiguous() for k, v in out.items()}, args.out)
    print(f"loss {loss.item():.6e}: wrote {args.out}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="mode", required=True)
    f = sub.add_parser("fit", help="train a model from an episodes file")
    f.add_argument("--data", required=True, help="training episodes file")
    f.add_argument("--out", required=True, help="drivesim weight file to write (f16)")
    f.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--base-channels", type=int, default=32)
    f.add_argument("--z-dim", type=int, default=128)
    f.add_argument("--hidden-dim", type=int, default=256)
    f.add_argument("--vae-steps", type=int, default=14000)
    f.add_argument("--batch", type=int, default=64)
    f.add_argument("--lr", type=float, default=ADAM_VAE_GAN["lr"])
    f.add_argument("--w-pixel", type=float, default=LOSS_WEIGHTS["pixel"], help="weight of the pixel L1 term")
    f.add_argument("--w-feature", type=float, default=LOSS_WEIGHTS["feature"], help="weight of the feature term")
    f.add_argument("--w-kl", type=float, default=LOSS_WEIGHTS["kl"], help="weight of the KL prior")
    f.add_argument("--w-gan", type=float, default=LOSS_WEIGHTS["gan"], help="weight of the generator's GAN term")
    f.add_argument("--max-minutes", type=float, default=math.inf, help="stop the VAE-GAN early after this")
    f.add_argument("--transition-steps", type=int, default=8000)
    f.add_argument("--transition-batch", type=int, default=256)
    f.add_argument("--transition-lr", type=float, default=1e-3)
    f.add_argument("--log-every", type=int, default=1000)
    f.add_argument("--dtype", default="f16", choices=["f32", "f16", "bf16"], help="dtype of the written weights")
    e = sub.add_parser("eval", help="evaluate a weight file on held-out episodes")
    e.add_argument("--weights", required=True)
    e.add_argument("--data", required=True, help="held-out episodes file")
    e.add_argument("--figures", required=True, help="folder for the PNGs and eval.json")
    e.add_argument("--seed-clip", help="also write the first 8 frames of the first episode here")
    s = sub.add_parser("step", help="one training step on a batch file (the Rust step's reference)")
    s.add_argument("--stage", required=True, choices=["transition", "vae-gan"])
    s.add_argument("--weights", required=True, help="drivesim weight file (f16/bf16 train on f32 copies)")
    s.add_argument("--batch", required=True, help="safetensors: transition `codes` [B,T,z] and `actions` [B,T-1,a], "
                   "f32; vae-gan `frames` [B,H,W,C] (uint8, or f32 in [-1, 1]), `eps` and `prior` [B,z] f32")
    s.add_argument("--out", required=True, help="safetensors to write: loss, grad.*, updated tensors")
    s.add_argument("--lr", type=float, help="Adam's learning rate (default 1e-3 transition, 2e-4 vae-gan)")
    s.add_argument("--teacher", type=int, default=TEACHER)
    s.add_argument("--clip", type=float, default=1.0)
    s.add_argument("--full-bptt", action="store_true", help="do not detach fed-back predictions")
    args = p.parse_args(argv)
    modes = {"fit": fit, "eval": evaluate, "step": step}
    try:
        modes[args.mode](args)
    except (episodes.EpisodesError, ValueError, OSError) as err:
        print(f"train: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()

"""The VAE-GAN stage (Larsen et al.): encoder, generator and a discriminator. The encoder
minimises the KL prior plus the reconstruction error, measured on the discriminator's 3rd conv
features and in pixels; the generator minimises the same reconstruction error and fools the
discriminator with both reconstructions and prior samples; the GAN gradient never reaches the
encoder."""

import contextlib
import json
import time

import torch
import torch.distributed as dist
from torch import nn
from torch.nn import functional as F

from drivesim_reference.checkpoints import restore_random
from drivesim_reference.distributed import average_gradients, global_var, share, world
from drivesim_reference.model import LEAK, _conv


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


def train_vae_gan(model, dis, frames, args, log, checkpoints, state=None):
    """Trains the encoder, generator and discriminator `dis` for --vae-steps (or --max-minutes),
    from the checkpoint `state` where it is one of this stage."""
    dev = frames.device
    enc, gen = model.encoder, model.generator
    adam = dict(ADAM_VAE_GAN, lr=args.lr)
    opts = [torch.optim.Adam(m.parameters(), **adam) for m in (enc, gen, dis)]
    amp = torch.autocast("cuda", torch.bfloat16) if dev.type == "cuda" else contextlib.nullcontext()
    weights = dict(kl=args.w_kl, feature=args.w_feature, pixel=args.w_pixel, gan=args.w_gan)
    gen_rng = torch.Generator(dev).manual_seed(args.seed)
    done, spent = 0, 0.0
    if state is not None:
        for opt, saved in zip(opts, state["optimisers"]):
            opt.load_state_dict(saved)
        restore_random(state, batches=gen_rng)
        done, spent = state["step"], state["seconds"]
    model.train()
    dis.train()
    start = time.time() - spent
    deadline = start + 60 * args.max_minutes
    for step in range(done + 1, args.vae_steps + 1):
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
        if checkpoints.due(step, args.vae_steps):
            checkpoints.save("vae_gan", step, model, dis, log, opts, batches=gen_rng, seconds=time.time() - start)
    model.eval()
    dis.eval()


def psnr(x, y):
    """Mean PSNR in dB of frames in [-1, 1], on the 0-255 scale."""
    mse = ((x.clamp(-1, 1) - y) * 127.5).square().flatten(1).mean(1)
    return float((10 * torch.log10(255.0**2 / mse.clamp_min(1e-10))).mean())

"""`train step`: one training step of a stage on a given batch, the Rust `train step`'s
reference (weights/TRAINING_FILES.md)."""

import torch
import torch.distributed as dist

from drivesim_reference.distributed import globalise_batch_norms, share, start_distributed, world
from drivesim_reference.model import load_discriminator, load_drivesim
from drivesim_reference.sequences import transition_step
from drivesim_reference.vae_gan import ADAM_VAE_GAN, Discriminator, to_input, vae_gan_step


def step(args):
    """`train step`: one training step of a stage on a batch file; see weights/TRAINING_FILES.md."""
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

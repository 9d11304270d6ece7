"""Train the drivesim networks as in the paper, and evaluate a weight file.

  weights/tool train fit --data train.safetensors.gz --out default.safetensors [--device cuda]
      [--checkpoint run.ckpt --checkpoint-every 500 --resume]
  weights/tool train eval --weights default.safetensors --data eval.safetensors.gz --figures figures/
  weights/tool train step --stage transition|vae-gan --weights W.safetensors --batch B.safetensors --out O.safetensors
  weights/tool train heads --head reward|value --weights W.safetensors --episodes E.safetensors.gz --out O.safetensors
  weights/tool train texture --weights W.safetensors --episodes E.safetensors.gz --out O.safetensors [--device cuda]
  weights/tool train latent --weights W.safetensors --episodes E.safetensors.gz --out O.safetensors [--device cuda]
  weights/tool train steering --weights W.safetensors --episodes E.safetensors.gz --branches B.safetensors.gz --out O.safetensors
  weights/tool train road --weights W.safetensors --sampler S.safetensors --windows RANK_DIR --out O.safetensors
  weights/tool train driver --weights W.safetensors --episodes E.safetensors.gz --out O.safetensors
  weights/tool train driver --weights W.safetensors --average A.safetensors,B.safetensors --out O.safetensors

fit: (1) VAE-GAN (vae_gan.py): encoder, generator and a discriminator. (2) The transition RNN
(sequences.py) on encoded 15-frame sequences: 5 frames teacher forced, then 10 with its own
output fed back, gradient stopped. Adam throughout. Both on the episodes and their mirror
images (frames flipped left to right, steering negated; --no-mirror: the episodes only).
With --spread the transition also learns the spread of its predictions (sequences.py's
`spread_loss`), which the crate's sampled futures draw from. With --checkpoint FILE it writes a
checkpoint every --checkpoint-every steps and at the end of the VAE-GAN; with --resume it goes
on from one, to the bytes the run that never stopped writes (checkpoints.py). The action
normalisation used in training is folded into U and b, so the exported model takes raw
(speed, steering). Writes the f16 drivesim file and a JSON log beside it.

step (reference_step.py): one training step of a stage on a given batch, writing the losses,
the gradients (for the transition, before clipping) and the updated tensors: the reference of
the Rust `train step` (weights/TRAINING_FILES.md). The VAE-GAN step reads the discriminator from the
weight file, where `fit` stores it (`discriminator.*`), so training can go on from either side.

heads (train_heads.py): the reward head or the value head (TD(λ)) on episodes with rewards,
added to a weight file: the twin of the Rust `train heads`.

texture (train_texture.py): the transition's texture net, a sampler trained adversarially so
that sampled futures keep the road's kerbs and grass patches, added to a weight file (PyTorch
only: the crate samples through it, it has no trainer of it).

latent (train_latent.py): the transition and its texture net trained together as a conditional
VAE, so that the futures sampled at temperature 1 draw what the state cannot know (the bend not
yet in view): the world that ranks drivers as the real track does (docs/judging.md).

steering (train_steering.py): the transition fine-tuned on paired steering branches (`python -m
drivesim branches`), so that it answers the steering as the real car does, apart from the road.

road (train_road.py): a texture net fine-tuned so that the roads it makes up past the view bend
as the real ones do (the unchanged clone steers there as on the real laps), several seeds, the
one whose dream fits the training family's real off-road shares best kept.

driver (train_driver.py): a driver learnt inside such a world by the gradient of the dream's own
return (its reward, off-road and value heads), from real starts, never an expert's label: the
file's policy replaced by it (docs/learning.md); --average writes several such drivers' mean as
one policy.

eval (evaluation.py): reconstruction PSNR, 1-step and 10-step latent prediction error, steering response,
a contact sheet of a 100-step rollout, all from frames the model never saw; and the fidelity
figures (`fidelity` in eval.json, weights/TRAINING_FILES.md §5): PSNR percentiles, the latent error
after 10 and 30 fed-back steps against the mean code, the road's direction under constant
steering, the fed-back codes' norm.
"""

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from drivesim import _files, episodes
from drivesim_reference import train_heads
from drivesim_reference import train_driver, train_latent, train_road, train_steering, train_texture
from drivesim_reference.checkpoints import Checkpoints
from drivesim_reference.distributed import globalise_batch_norms, start_distributed, world
from drivesim_reference.model import Config, DriveSim, save_drivesim
from drivesim_reference.reference_step import step
from drivesim_reference.sequences import SEQ, TEACHER, encode, noise_factor, sharpen_noise, train_transition
from drivesim_reference.vae_gan import ADAM_VAE_GAN, LOSS_WEIGHTS, Discriminator, train_vae_gan


def fit(args):
    rank, dev = start_distributed(args.device)
    if rank:  # one process reports
        sys.stdout = open(os.devnull, "w")
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    data = episodes.read(args.data)
    if not args.no_mirror:  # left and right learned from the same drives
        data = data.with_mirror_images()
    cfg = Config(height=data.frames.shape[1], width=data.frames.shape[2], channels=3,
                 base_channels=args.base_channels, z_dim=args.z_dim, hidden_dim=args.hidden_dim, action_dim=2)
    frames = torch.from_numpy(data.frames).to(dev)
    print(f"{len(data)} episodes, {len(frames)} frames, config {cfg}", flush=True)
    model = globalise_batch_norms(DriveSim(cfg, spread=args.spread).to(dev))
    dis = globalise_batch_norms(Discriminator(cfg).to(dev))
    checkpoints = Checkpoints(args, dev)
    if not rank:
        checkpoints.remove_leftovers()
    state = checkpoints.restore()
    if state is None:
        log = [dict(args={k: str(v) for k, v in vars(args).items()}, config=json.loads(cfg.to_json()),
                    episodes=len(data), frames=len(frames))]
    else:
        model.load_state_dict(state["model"])
        dis.load_state_dict(state["discriminator"])
        log = state["log"] + [dict(resumed=state["stage"], step=state["step"])]
        print(f"resuming from {args.checkpoint}: {state['stage']} step {state['step']}", flush=True)
    t0 = time.time()
    if state is None or state["stage"] == "vae_gan":
        train_vae_gan(model, dis, frames, args, log, checkpoints, state)
        state = None
        checkpoints.save("transition", 0, model, dis, log)  # the encoder is final from here
    model.eval()  # the codes from the running statistics, resumed or not
    dis.eval()
    t1 = time.time()
    codes = encode(model, frames)
    actions = torch.from_numpy(data.actions).to(dev)
    norm = train_transition(model, dis, codes, actions, data.windows(SEQ), args, log, checkpoints, state)
    if args.spread:  # the correlation of the sampled noise, from the training drives' one-step errors
        model.transition.set_noise_factor(sharpen_noise(noise_factor(model.transition.cpu(), [
            (codes[a:b], actions[a:b]) for a, b in data.bounds()]), args.noise_power).to(dev))
        model.transition.to(dev)
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


def evaluate(args):
    """`eval` (evaluation.py), imported here: its real-car probe needs gymnasium, the trainers do not."""
    from drivesim_reference.evaluation import evaluate as run

    run(args)


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
    f.add_argument("--spread", action="store_true", help="also train the transition's spread head (sampled "
                   "futures: the log standard deviation of each predicted code, S h' + s)")
    f.add_argument("--noise-power", type=int, choices=range(1, 9), default=1, metavar="1..8",
                   help="with --spread: raise the noise's correlation to this power, back to unit diagonal "
                   "(sequences.sharpen_noise, the crate's `train noise --noise-power`): 2 brings the best of a "
                   "few sampled futures nearer what happened and makes the sampled codes smaller")
    f.add_argument("--no-mirror", action="store_true", help="train on the episodes only, not also on their mirror "
                   "images (frames flipped left to right, steering negated)")
    f.add_argument("--checkpoint", help="checkpoint file: written every --checkpoint-every steps, read by --resume")
    f.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    f.add_argument("--resume", action="store_true",
                   help="go on from --checkpoint where it exists (a run of the same arguments); start afresh where not")
    e = sub.add_parser("eval", help="evaluate a weight file on held-out episodes")
    e.add_argument("--weights", required=True)
    e.add_argument("--data", required=True, help="held-out episodes file")
    e.add_argument("--figures", required=True, help="folder for the PNGs and eval.json")
    e.add_argument("--seed-clip", help="also write the first 8 frames of the first episode here")
    e.add_argument("--reference", help="episodes the model trained on: futures made of their real codes "
                   "as a baseline for the sampled futures (futures.real_futures)")
    e.add_argument("--probe-real", action="store_true", help="also the steering probe of the real car on the same "
                   "starts (drivesim.carracing.probe_real; computed once per --data, cached beside it) and the dream's gaps to it")
    e.add_argument("--workers", type=int, default=os.cpu_count(), help="processes for --probe-real's first run")
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
    h = sub.add_parser("heads", help="train the reward or the value head on episodes with rewards (the Rust "
                       "`train heads`'s twin)")
    h.add_argument("--weights", required=True, help="weight file to start from (its encoder and transition give "
                   "the head's input)")
    h.add_argument("--episodes", required=True, help="episodes with rewards (`reward`, `on_road`) to learn from")
    h.add_argument("--heldout", help="episodes to evaluate on; without it, the last --holdout episodes of --episodes")
    h.add_argument("--holdout", type=int, default=1, help="episodes of --episodes held out without --heldout")
    h.add_argument("--out", required=True, help="where to write the weights with the trained head")
    h.add_argument("--head", required=True, choices=["reward", "value"], help="which head to train")
    h.add_argument("--steps", type=int, default=4000)
    h.add_argument("--batch", type=int, default=256, help="examples per step")
    h.add_argument("--lr", type=float, default=1e-3, help="peak learning rate (cosine decay to zero)")
    h.add_argument("--width", type=int, default=64, help="units of a new head's hidden layer (a head the file "
                   "has keeps its own)")
    h.add_argument("--discount", type=float, default=0.98, help="the value's discount per decision")
    h.add_argument("--lambda", dest="lam", metavar="LAMBDA", type=float, default=0.95, help="TD(λ)'s λ")
    h.add_argument("--refresh", type=int, default=500, help="steps between recomputing the value's targets "
                   "with the head as trained so far")
    h.add_argument("--dream-steps", type=int, default=0, help="the value head also learns from dreamed drives "
                   "of this many decisions (0: real drives only): the policy driving on from real states over "
                   "sampled futures, the reward head scoring them (the file needs both)")
    h.add_argument("--dream-every", type=int, default=4, help="a dreamed drive from every this many real states")
    h.add_argument("--restart", action="store_true", help="start a new head even where the file has one")
    h.add_argument("--seed", type=int, default=0, help="seed of a new head's weights and of the examples' order")
    h.add_argument("--no-mirror", action="store_true", help="train on the episodes only, not also on their "
                   "mirror images (frames flipped left to right, steering negated)")
    train_texture.add_arguments(sub.add_parser("texture", help="train the transition's texture net, a sampler "
                                               "whose futures keep the road's texture (train_texture.py)"))
    train_latent.add_arguments(sub.add_parser("latent", help="train the transition and its texture net together "
                                              "as a conditional VAE: sampled futures that draw what the state "
                                              "cannot know (train_latent.py)"))
    train_steering.add_arguments(sub.add_parser("steering", help="fine-tune the transition's answer to the steering "
                                                "on paired branches (train_steering.py)"))
    train_road.add_arguments(sub.add_parser("road", help="fine-tune the texture net so that its made-up roads bend "
                                            "as the real ones do (train_road.py)"))
    train_driver.add_arguments(sub.add_parser("driver", help="learn a driver inside the dream by the gradient of "
                                              "the dream's own return (train_driver.py)"))
    args = p.parse_args(argv)
    modes = {"fit": fit, "eval": evaluate, "step": step, "heads": train_heads.heads, "texture": train_texture.texture,
             "latent": train_latent.latent, "steering": train_steering.steering, "road": train_road.road,
             "driver": train_driver.driver}
    try:
        modes[args.mode](args)
    except (episodes.EpisodesError, ValueError, OSError) as err:
        print(f"train: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()

"""Generate the Rust test fixtures in tests/fixtures/, or check the committed ones.

    weights/tool fixtures            regenerate tests/fixtures/
    weights/tool fixtures --check    regenerate into a temp dir and compare

For each fixture NAME this writes NAME.safetensors (random weights in the
drivesim format), NAME.io.safetensors (float32 inputs and reference outputs,
frames HWC) and NAME.train.safetensors (a batch of transition training windows,
the first step's loss, gradients and updated tensors, and the tensors after ten
steps, from reference_step.py's); for some, NAME.gan.safetensors (the weights with a
discriminator) and NAME.gan.io.safetensors (a VAE-GAN batch, the first step's
losses, gradients and updated tensors, and the tensors after five steps). See
weights/TRAINING_FILES.md for the tensor names. heads_f32.train.safetensors holds a reward head's
steps (heads.py's HeadTrainer) and a drive's λ-returns, for tests/heads_parity.rs.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from drivesim_reference.heads import HeadTrainer, lambda_returns
from drivesim_reference.model import CONFIG_KEY, Config, DriveSim, Head, load_discriminator, load_drivesim, save_drivesim
from drivesim_reference.sequences import noise_factor, sharpen_noise, transition_step
from drivesim_reference.vae_gan import ADAM_VAE_GAN, Discriminator, vae_gan_step

OUT = Path(__file__).resolve().parents[2] / "tests" / "fixtures"
# Another CPU's float32 sums differ by a few 1e-6 of a tensor's scale (Intel AVX-512 against the
# AMD AVX2 machine that wrote the fixtures: up to 3e-6); a change to the reference moves far more.
RTOL = 1e-5
# The convolutions followed by BatchNorm, whose bias gradients are zero in exact arithmetic.
BEFORE_NORM = re.compile(r"\.(conv[123]|convs\.[123]|deconv[123])\.bias$")
TRANSITION_STEPS = 30
ROLLOUT_SEEDS = 3
ROLLOUT_PREDICTIONS = 5

# Transition training fixtures: windows per batch, Adam steps compared, learning rate.
TRAIN_BATCH, TRAIN_STEPS, TRAIN_LR = 3, 10, 1e-3
# name: (codes per window, teacher-forced inputs, gradient clip norm). The two small fixtures use
# the paper's windows; the others shorter ones with the teacher boundary elsewhere. The first
# gradient norms are 2.2-2.9: wide_f32's clip of 5 leaves its gradients as they are while the
# others' are scaled down, so both sides of clip_grad_norm_ are checked.
TRAIN_WINDOWS = {
    "small_f32": (15, 5, 1.0),
    "small_f16": (15, 5, 1.0),
    "tiny_bf16": (9, 3, 1.0),
    "tall_f32": (9, 3, 1.0),
    "wide_f32": (9, 3, 5.0),
    "spread_f32": (12, 4, 1.0),
}

# VAE-GAN fixtures: frames per batch (BatchNorm statistics over few items), and the Adam steps
# after which the tensors are compared again.
GAN_BATCH = {"small_f32": 3, "wide_f32": 2, "tiny_bf16": 2}
# The steps run at a tenth of the training rate: at 2e-4 the trajectory of these tiny random
# batches is chaotic (Adam moves every weight by about ±lr, activations cross their kinks, and
# PyTorch's own float32 run is 65% away from its float64 run in gradient after five steps),
# so only a slower run can check the bookkeeping of several steps against the exact one.
GAN_STEPS, GAN_STEPS_LR = 5, 2e-5

# name: (config, dtype, seed)
FIXTURES = {
    "small_f32": (Config(48, 112, 3, 6, z_dim=20, hidden_dim=36, action_dim=2), "f32", 1),
    "small_f16": (Config(48, 112, 3, 6, z_dim=20, hidden_dim=36, action_dim=2), "f16", 2),
    "tiny_bf16": (Config(16, 32, 1, 3, z_dim=5, hidden_dim=7, action_dim=2), "bf16", 3),
    "tall_f32": (Config(64, 32, 4, 5, z_dim=9, hidden_dim=11, action_dim=3), "f32", 4),
    # Eight channels on a 16x32 plane: the encoder's second and the generator's third layer
    # take 4x4 Winograd tiles.
    "wide_f32": (Config(32, 64, 3, 8, z_dim=12, hidden_dim=16, action_dim=2), "f32", 5),
    # The transition's spread head (sampled futures): its loss, gradients and steps.
    "spread_f32": (Config(32, 64, 3, 4, z_dim=10, hidden_dim=14, action_dim=2), "f32", 6),
}
SPREAD = {"spread_f32"}

# The head trainer's fixture: the Rust tests' SMALL config, a reward head of HEAD_WIDTH units
# trained in HEAD_UNITS for HEAD_STEPS Adam steps of HEAD_BATCH examples; one drive's λ-returns.
HEAD_CONFIG = Config(16, 32, 3, 3, z_dim=12, hidden_dim=40, action_dim=2)
# The texture_f32 fixture's texture net (HEAD_CONFIG's model).
TEXTURE_WIDTH = 9
HEAD_WIDTH, HEAD_BATCH, HEAD_STEPS, HEAD_LR = 20, 7, 3, 0.01
HEAD_UNITS = [(1.5, 2.0), (0.3, 0.45)]
RETURNS_T, RETURNS_DISCOUNT, RETURNS_LAMBDA = 9, 0.9, 0.8


def randomize(model: torch.nn.Module) -> None:
    """Random weights whose outputs depend clearly on every layer.

    PyTorch's default init shrinks the signal at each layer, so generated frames
    would hardly depend on z; He-style scaling keeps it alive. BN and biases are
    made non-trivial so that BN folding and bias handling are tested.
    """
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)):
                fan_in = m.weight[0].numel()
                m.weight.normal_(0, (2 / fan_in) ** 0.5)
                m.bias.normal_(0, 0.1)
            elif isinstance(m, torch.nn.ConvTranspose2d):
                # Stride 2: each output pixel sees about a quarter of the k*k taps.
                fan_in = m.weight.shape[0] * m.weight[0, 0].numel() / 4
                m.weight.normal_(0, (2 / fan_in) ** 0.5)
                m.bias.normal_(0, 0.1)
            elif isinstance(m, torch.nn.BatchNorm2d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.normal_(0, 0.1)
                m.running_mean.normal_(0, 0.1)
                m.running_var.uniform_(0.5, 1.5)
        if isinstance(model, DriveSim):
            model.transition.b.normal_(0, 0.1)
            model.transition.a.normal_(0, 0.1)
            if model.transition.spread:  # spreads of about 0.5 to 2
                model.transition.S.normal_(0, 0.3 * model.cfg.hidden_dim ** -0.5)
                model.transition.s.normal_(0, 0.3)


def hwc(frames: torch.Tensor) -> torch.Tensor:
    return frames.permute(0, 2, 3, 1).contiguous()


def nchw(frames: torch.Tensor) -> torch.Tensor:
    return frames.permute(0, 3, 1, 2)


def frames(n: int, cfg: Config) -> torch.Tensor:
    return torch.rand(n, cfg.height, cfg.width, cfg.channels) * 2 - 1


@torch.no_grad()
def reference_io(model: DriveSim, cfg: Config) -> dict[str, torch.Tensor]:
    io = {}

    io["encode.frames"] = frames(2, cfg)
    io["encode.mean"], io["encode.logsigma"] = model.encoder(nchw(io["encode.frames"]))

    io["generate.z"] = torch.randn(2, cfg.z_dim)
    io["generate.frames"] = hwc(model.generator(io["generate.z"]))

    z = io["transition.z0"] = torch.randn(cfg.z_dim)
    h = io["transition.h0"] = torch.randn(cfg.hidden_dim) * 0.5
    actions = io["transition.actions"] = torch.randn(TRANSITION_STEPS, cfg.action_dim)
    zs, hs = [], []
    for c in actions:
        z, h = model.transition(z, h, c)
        zs.append(z)
        hs.append(h)
    io["transition.z"], io["transition.h"] = torch.stack(zs), torch.stack(hs)
    io["transition.frame"] = hwc(model.generator(zs[-1][None]))[0]

    io["rollout.seed_frames"] = frames(ROLLOUT_SEEDS, cfg)
    io["rollout.actions"] = torch.randn(ROLLOUT_SEEDS - 1 + ROLLOUT_PREDICTIONS, cfg.action_dim)
    io["rollout.codes"] = model.rollout(nchw(io["rollout.seed_frames"]), io["rollout.actions"])
    io["rollout.frames"] = hwc(model.generator(io["rollout.codes"]))

    return {k: v.float().contiguous() for k, v in io.items()}


def reference_train(model: DriveSim, cfg: Config, name: str, seed: int) -> tuple[dict, dict]:
    """A batch of windows, one training step's loss, gradients (detached feedback as in the
    paper, and full back-propagation as `full.`) and updated tensors, and the tensors after
    TRAIN_STEPS steps on the same batch; with the metadata the Rust test reads."""
    window, teacher, clip = TRAIN_WINDOWS[name]
    # A generator of its own: the other fixtures' draws stay as they were.
    g = torch.Generator().manual_seed(1000 + seed)
    codes = torch.randn(TRAIN_BATCH, window, cfg.z_dim, generator=g)
    actions = torch.randn(TRAIN_BATCH, window - 1, cfg.action_dim, generator=g) * 0.5
    actions[..., 0] = 20 + 5 * torch.randn(TRAIN_BATCH, window - 1, generator=g)
    io = {"codes": codes, "actions": actions}
    if model.transition.spread:  # the noise's correlation from the windows' one-step errors, at the start
        io["noise_factor"] = noise_factor(model.transition, list(zip(codes, actions)))
        io["noise_factor_power2"] = sharpen_noise(io["noise_factor"], 2)
    start = {k: p.detach().clone() for k, p in model.transition.named_parameters()}

    def run(steps, detach):
        with torch.no_grad():
            for k, p in model.transition.named_parameters():
                p.copy_(start[k])
        opt = torch.optim.Adam(model.transition.parameters(), lr=TRAIN_LR)
        results = [transition_step(model.transition, opt, codes, actions, teacher, clip, detach)
                   for _ in range(steps)]
        tensors = {f"transition.{k}": p.detach().clone() for k, p in model.transition.named_parameters()}
        return results[0], tensors

    (loss, grads), io_after1 = run(1, True)
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads.values()]))
    print(f"{name}: loss {loss.item():.4f}, gradient norm {norm.item():.3f} (clip {clip})")
    io["loss"] = loss.reshape(1)
    io.update({f"grad.transition.{k}": v for k, v in grads.items()})
    io.update(io_after1)
    (loss, grads), _ = run(1, False)
    io["full.loss"] = loss.reshape(1)
    io.update({f"full.grad.transition.{k}": v for k, v in grads.items()})
    _, after = run(TRAIN_STEPS, True)
    io.update({f"after{TRAIN_STEPS}.{k}": v for k, v in after.items()})
    meta = {"teacher": str(teacher), "lr": str(TRAIN_LR), "clip": str(clip), "steps": str(TRAIN_STEPS)}
    return {k: v.float().contiguous() for k, v in io.items()}, meta


def reference_vae_gan(model: DriveSim, cfg: Config, dtype: str, name: str, seed: int, out: Path) -> dict:
    """Writes NAME.gan.safetensors (the weights with a random discriminator) and returns a batch
    (frames HWC in [-1, 1], eps, prior), one VAE-GAN step's losses, gradients and updated
    tensors (running statistics included), and the tensors after GAN_STEPS steps on the batch."""
    batch = GAN_BATCH[name]
    g = torch.Generator().manual_seed(2000 + seed)
    frames_u8 = torch.randint(0, 256, (batch, cfg.height, cfg.width, cfg.channels), generator=g, dtype=torch.uint8)
    io = {"frames": frames_u8.float() / 127.5 - 1.0}
    io["eps"], io["prior"] = (torch.randn(batch, cfg.z_dim, generator=g) for _ in range(2))
    torch.manual_seed(3000 + seed)
    dis = Discriminator(cfg)
    randomize(dis)
    path = out / f"{name}.gan.safetensors"
    save_drivesim(model, cfg, path, dtype, discriminator=dis)
    # Train on the tensors as stored (rounded for f16/bf16), in float32.
    model, _ = load_drivesim(path)
    dis.load_state_dict(load_discriminator(path), strict=False)
    model.train()
    dis.train()
    nets = dict(encoder=model.encoder, generator=model.generator, discriminator=dis)

    def state(prefix):
        return {f"{prefix}{net}.{k}": v.detach().clone() for net, m in nets.items()
                for k, v in m.state_dict().items() if not k.endswith("num_batches_tracked")}

    start = {net: {k: v.clone() for k, v in m.state_dict().items()} for net, m in nets.items()}

    def run(dtype, steps, lr):
        """`steps` steps from the start in `dtype`: the losses of each, the first's gradients."""
        for net, m in nets.items():
            m.to(dtype).load_state_dict(start[net])
        opts = [torch.optim.Adam(m.parameters(), **dict(ADAM_VAE_GAN, lr=lr)) for m in nets.values()]
        x, eps, prior = nchw(io["frames"]).to(dtype), io["eps"].to(dtype), io["prior"].to(dtype)
        every = [vae_gan_step(model.encoder, model.generator, dis, opts, x, eps, prior)[:2] for _ in range(steps)]
        return every[0], torch.stack([torch.stack(list(losses.values())) for losses, _ in every])

    # Each run in float32 (PyTorch as users run it) and in float64 (the reference both are
    # measured against: Adam's first step moves every weight by about ±lr whatever the size of
    # its gradient, so rounding alone moves float32 weights by up to 1e-3 of their scale).
    for dtype, prefix in ((torch.float32, ""), (torch.float64, "f64.")):
        (losses, grads), _ = run(dtype, 1, ADAM_VAE_GAN["lr"])
        io.update({f"{prefix}loss.{k}": v.reshape(1) for k, v in losses.items()})
        for net, m in nets.items():
            io.update({f"{prefix}grad.{net}.{k}": gr for (k, _), gr in zip(m.named_parameters(), grads[net])})
        io.update(state(prefix))
        if not prefix:
            print(f"{name}: VAE-GAN losses " + ", ".join(f"{k} {v.item():.4f}" for k, v in losses.items()))
        _, every = run(dtype, GAN_STEPS, GAN_STEPS_LR)
        io[f"{prefix}losses"] = every  # [step, (d, e, g, gan, feature, pixel_l1, kl)]
        io.update(state(f"{prefix}after{GAN_STEPS}."))
    return {k: v.float().contiguous() for k, v in io.items()}


def reference_heads(out: Path) -> None:
    """Writes heads_f32.train.safetensors: a reward head's tensors (`initial.reward.*`, PyTorch's
    default draw), each step's batch (`step{i}.inputs` [batch, z+h], `.targets` [batch, 2]: a
    reward about the units' and an off-road flag of 0 or 1), the losses before each step, the
    tensors after them (`final.reward.*`), the units [2, 2]; and `returns.rewards`,
    `returns.next_values`, `returns.expected` of one drive."""
    cfg = HEAD_CONFIG
    g = torch.Generator().manual_seed(4000)
    torch.manual_seed(4000)
    head = Head(cfg, HEAD_WIDTH, "reward")
    trainer = HeadTrainer(head, HEAD_UNITS)
    io = {f"initial.reward.{k}": v.detach().clone() for k, v in head.state_dict().items()}
    io["units"] = torch.tensor(HEAD_UNITS)
    losses = []
    for i in range(HEAD_STEPS):
        z = torch.randn(HEAD_BATCH, cfg.z_dim, generator=g)
        h = torch.rand(HEAD_BATCH, cfg.hidden_dim, generator=g) * 2 - 1
        reward = 1.5 + 2.0 * torch.randn(HEAD_BATCH, generator=g)
        off = (torch.rand(HEAD_BATCH, generator=g) < 0.3).float()
        io[f"step{i}.inputs"] = inputs = torch.cat([z, h], 1)
        io[f"step{i}.targets"] = targets = torch.stack([reward, off], 1)
        losses.append(trainer.step(inputs, targets, HEAD_LR))
    io["losses"] = torch.tensor(losses)
    io.update({f"final.{k}": v for k, v in trainer.tensors().items()})
    rewards = torch.randn(RETURNS_T, generator=g)
    next_values = 3 * torch.randn(RETURNS_T, generator=g)
    io["returns.rewards"], io["returns.next_values"] = rewards, next_values
    io["returns.expected"] = lambda_returns(rewards, next_values, RETURNS_DISCOUNT, RETURNS_LAMBDA)
    print("heads_f32: losses " + ", ".join(f"{v:.4f}" for v in losses))
    meta = {CONFIG_KEY: cfg.to_json(), "kind": "reward", "width": str(HEAD_WIDTH), "batch": str(HEAD_BATCH),
            "steps": str(HEAD_STEPS), "lr": str(HEAD_LR), "discount": str(RETURNS_DISCOUNT),
            "lambda": str(RETURNS_LAMBDA)}
    save_file({k: v.float().contiguous() for k, v in io.items()}, str(out / "heads_f32.train.safetensors"),
              metadata=meta)


def reference_texture(out: Path) -> None:
    """Writes texture_f32.safetensors (HEAD_CONFIG's random model with a texture net of width
    TEXTURE_WIDTH whose noise columns are zero, so that its offset is a function of h alone) and
    texture_f32.io.safetensors: `h` [n, hd], `mean` [n, z] and `sampled` [n, z], the mean plus
    the net's offset, the crate's `Simulator::sample` at any temperature and seed."""
    cfg, n = HEAD_CONFIG, 5
    torch.manual_seed(5000)
    model = DriveSim(cfg, texture_width=TEXTURE_WIDTH)
    randomize(model)
    with torch.no_grad():
        model.transition.texture.hidden.weight[:, :cfg.z_dim] = 0
    weights = out / "texture_f32.safetensors"
    save_drivesim(model, cfg, weights, "f32")
    net = load_drivesim(weights)[0].transition.texture
    g = torch.Generator().manual_seed(5001)
    h = torch.rand(n, cfg.hidden_dim, generator=g) * 2 - 1
    mean = torch.randn(n, cfg.z_dim, generator=g)
    with torch.no_grad():
        sampled = mean + net(torch.zeros(n, cfg.z_dim), h)
    save_file(dict(h=h, mean=mean, sampled=sampled.contiguous()), str(out / "texture_f32.io.safetensors"),
              metadata={CONFIG_KEY: cfg.to_json()})


def generate(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, (cfg, dtype, seed) in FIXTURES.items():
        torch.manual_seed(seed)
        model = DriveSim(cfg, spread=name in SPREAD)
        randomize(model)
        weights = out / f"{name}.safetensors"
        save_drivesim(model, cfg, weights, dtype)
        # Reference outputs use the weights as stored (rounded for f16/bf16), in float32.
        model, _ = load_drivesim(weights)
        meta = {CONFIG_KEY: cfg.to_json(), "drivesim.frame_layout": "HWC"}
        save_file(reference_io(model, cfg), str(out / f"{name}.io.safetensors"), metadata=meta)
        train_io, train_meta = reference_train(model, cfg, name, seed)
        save_file(train_io, str(out / f"{name}.train.safetensors"), metadata=train_meta)
        if name in GAN_BATCH:
            torch.manual_seed(seed)
            model = DriveSim(cfg)
            randomize(model)
            gan_io = reference_vae_gan(model, cfg, dtype, name, seed, out)
            meta = {"lr": str(ADAM_VAE_GAN["lr"]), "steps": str(GAN_STEPS), "steps_lr": str(GAN_STEPS_LR)}
            save_file(gan_io, str(out / f"{name}.gan.io.safetensors"), metadata=meta)
    reference_heads(out)
    reference_texture(out)


def compare(committed: Path, fresh: Path) -> list[str]:
    """Differences between two safetensors files (metadata exactly, tensors within RTOL)."""
    if not committed.exists():
        return [f"{committed.name}: missing"]
    errors = []
    with safe_open(str(committed), "pt") as a, safe_open(str(fresh), "pt") as b:
        if a.metadata() != b.metadata():
            errors.append(f"{committed.name}: metadata {a.metadata()} != {b.metadata()}")
        lr = float((b.metadata() or {}).get("lr", 0.0))
    old, new = load_file(str(committed)), load_file(str(fresh))
    if old.keys() != new.keys():
        errors.append(f"{committed.name}: tensor names differ: {sorted(old.keys() ^ new.keys())}")
    for k in sorted(old.keys() & new.keys()):
        x, y = old[k], new[k]
        if x.dtype != y.dtype or x.shape != y.shape:
            errors.append(f"{committed.name}: {k}: {x.dtype}{list(x.shape)} != {y.dtype}{list(y.shape)}")
            continue
        problem = difference(k, x.double(), y.double(), old, new, lr)
        if problem:
            errors.append(f"{committed.name}: {k}: {problem}")
    return errors


def relative(x, y):
    """max |x - y| / max |y|: the error relative to the tensor's scale (element-wise relative
    error is meaningless near zero)."""
    return (x - y).abs().max().item() / max(y.abs().max().item(), 1e-30) if x.numel() else 0.0


def difference(k, x, y, old, new, lr):
    """What is wrong with the fresh value `y` of tensor `k` against the committed `x`, or None.

    A float32 result of the VAE-GAN step has its float64 twin (`f64.` + k), the exact step the
    Rust tests compare with. Another CPU's PyTorch sums convolutions in another order, and Adam
    moves each weight by about ±lr whatever its gradient's size, so its float32 results differ
    from the committed ones by far more than rounding; what must hold is what the Rust tests ask
    of drivesim: as close to the exact step as the committed float32 run was (3x, or 1e-4). The
    gradient of a bias before BatchNorm is zero in exact arithmetic (rounding noise on both
    sides): it must stay within 1e-5 of its layer's weight gradient, 1e-12 in float64 (the committed
    run's are 1e-17 to 4e-15 of it; another CPU's rounding gives others). A weight after the one step
    (`lr`), as the Rust tests check drivesim's: within 1e-4 of the tensor's scale of the exact
    step, or 2 lr where the exact gradient is within rounding of zero (Adam's first step moves a
    weight by lr, its direction the gradient's sign). The losses of that step within 1e-4;
    everything else (the float64 values, every other fixture) within RTOL."""
    twin = "f64." + k.removeprefix("f64.")
    if twin in new and twin.startswith("f64.grad.") and BEFORE_NORM.search(k):
        scale = new[twin.removesuffix(".bias") + ".weight"].double().abs().max().item()
        worst = max(y.abs().max().item(), new[twin].double().abs().max().item())
        bound = (1e-12 if k == twin else 1e-5) * scale
        return f"{worst:.3g}, not rounding's zero (weights' gradient {scale:.3g})" if worst > bound else None
    if twin != k and twin in new:
        exact = new[twin].double()
        grad = new.get("f64.grad." + k)
        if not k.startswith(("grad.", "after5.")) and grad is not None:
            grad = grad.double().abs()
            undetermined = (grad < 1e-3 * grad.max()) | bool(BEFORE_NORM.search(k))
            allowed = 1e-4 * exact.abs().max() + 2 * lr * undetermined
            worst = ((y - exact).abs() - allowed).max().item()
            return f"{worst:.3g} past the one step's bound" if worst > 0 else None
        ours, theirs = relative(y, exact), relative(x, old[twin].double())
        return f"{ours:.3g} from float64, the committed run {theirs:.3g}" if ours > max(1e-4, 3 * theirs) else None
    tolerance = 1e-4 if k == "losses" or k.startswith("loss.") else RTOL
    err = relative(x, y)
    return f"max difference {err:.3g} of the tensor's scale" if err > tolerance else None


def check() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        generate(Path(tmp))
        expected = sorted(p.name for p in Path(tmp).iterdir())
        errors = [e for name in expected for e in compare(OUT / name, Path(tmp) / name)]
    stale = sorted({p.name for p in OUT.glob("*.safetensors")} - set(expected))
    errors += [f"{name}: not produced by fixtures.py" for name in stale]
    for e in errors:
        print(e, file=sys.stderr)
    print(f"{len(expected)} fixture files checked, {len(errors)} problems")
    return 1 if errors else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--check", action="store_true", help="compare regenerated fixtures with tests/fixtures/")
    args = p.parse_args()
    torch.set_num_threads(1)  # one thread: a fixed summation order, reproducible results
    if args.check:
        return check()
    generate(OUT)
    print(f"wrote {len(FIXTURES) * 2} files to {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

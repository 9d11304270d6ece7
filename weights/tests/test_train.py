"""The training steps and fit, in one process and under torchrun: weights/tool -m pytest tests/test_train.py"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from drivesim_reference import train
from drivesim_reference.sequences import predict, transition_step
from drivesim_reference.vae_gan import Discriminator, vae_gan_step
from drivesim_reference.model import Config, DriveSim, save_drivesim

# weights/: the package drivesim_reference runs from here whether or not it is installed.
HERE = Path(__file__).resolve().parents[1]

CFG = Config(16, 32, 2, 3, z_dim=5, hidden_dim=7, action_dim=3)


def windows(batch=2, window=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, window, CFG.z_dim, generator=g), torch.randn(batch, window - 1, CFG.action_dim, generator=g)


def test_full_bptt_gradient_matches_finite_differences():
    # With full back-propagation the step's gradient is the loss's derivative.
    torch.manual_seed(0)
    tr = DriveSim(CFG).transition.double()
    z, c = (t.double() for t in windows())
    opt = torch.optim.SGD(tr.parameters(), lr=0.0)  # the gradients, no update
    _, grads = transition_step(tr, opt, z, c, teacher=2, clip=1e9, detach=False)
    eps = 1e-6
    for name, p in tr.named_parameters():
        direction = torch.randn_like(p)
        with torch.no_grad():
            p += eps * direction
            up = torch.nn.functional.mse_loss(predict(tr, z, c, 2), z[:, 1:])
            p -= 2 * eps * direction
            down = torch.nn.functional.mse_loss(predict(tr, z, c, 2), z[:, 1:])
            p += eps * direction
        numeric = (up - down) / (2 * eps)
        analytic = (grads[name] * direction).sum()
        assert abs(numeric - analytic) <= 1e-6 * max(1.0, abs(numeric)), name


def test_detach_changes_only_fed_back_gradients():
    torch.manual_seed(1)
    z, c = windows(window=5)
    results = []
    for detach in (True, False):
        torch.manual_seed(1)
        tr = DriveSim(CFG).transition
        opt = torch.optim.SGD(tr.parameters(), lr=0.0)
        results.append(transition_step(tr, opt, z, c, teacher=4, clip=1e9, detach=detach)[1])
    # Every input teacher-forced (teacher = T - 1): nothing is fed back, both agree.
    for name in results[0]:
        assert torch.equal(results[0][name], results[1][name]), name


def test_step_command_writes_every_tensor(tmp_path):
    torch.manual_seed(2)
    weights, batch, out = tmp_path / "w.safetensors", tmp_path / "b.safetensors", tmp_path / "o.safetensors"
    save_drivesim(DriveSim(CFG), CFG, weights, "f32")
    z, c = windows()
    save_file({"codes": z, "actions": c}, str(batch))
    train.main(["step", "--stage", "transition", "--weights", str(weights), "--batch", str(batch), "--out", str(out)])
    got = load_file(str(out))
    names = ["W", "V", "U", "b", "A", "a"]
    assert set(got) == {"loss"} | {f"grad.transition.{n}" for n in names} | {f"transition.{n}" for n in names}
    assert got["loss"].shape == (1,) and got["grad.transition.W"].shape == (CFG.hidden_dim, CFG.hidden_dim)


def test_step_command_rejects_bad_batches(tmp_path, capsys):
    weights, batch = tmp_path / "w.safetensors", tmp_path / "b.safetensors"
    save_drivesim(DriveSim(CFG), CFG, weights, "f32")
    z, c = windows()
    save_file({"codes": z, "actions": c[:, :-1].contiguous()}, str(batch))
    with pytest.raises(SystemExit) as exit:
        train.main(["step", "--stage", "transition", "--weights", str(weights), "--batch", str(batch),
                    "--out", str(tmp_path / "o.safetensors")])
    assert exit.value.code == 2 and "actions" in capsys.readouterr().err


def gan_files(tmp_path, with_discriminator=True):
    """A small weight file (with a discriminator) and a VAE-GAN batch of uint8 frames."""
    torch.manual_seed(3)
    weights, batch = tmp_path / "w.safetensors", tmp_path / "b.safetensors"
    dis = Discriminator(CFG) if with_discriminator else None
    save_drivesim(DriveSim(CFG), CFG, weights, "f32", discriminator=dis)
    g = torch.Generator().manual_seed(4)
    frames = torch.randint(0, 256, (4, CFG.height, CFG.width, CFG.channels), generator=g, dtype=torch.uint8)
    save_file({"frames": frames, "eps": torch.randn(4, CFG.z_dim, generator=g),
               "prior": torch.randn(4, CFG.z_dim, generator=g)}, str(batch))
    return weights, batch


def test_vae_gan_step_command_writes_every_tensor(tmp_path):
    weights, batch = gan_files(tmp_path)
    out = tmp_path / "o.safetensors"
    train.main(["step", "--stage", "vae-gan", "--weights", str(weights), "--batch", str(batch), "--out", str(out)])
    got = load_file(str(out))
    model, dis = DriveSim(CFG), Discriminator(CFG)
    params = [f"{net}.{k}" for net, m in (("encoder", model.encoder), ("generator", model.generator),
                                          ("discriminator", dis)) for k, _ in m.named_parameters()]
    stats = [f"{net}.{k}" for net, m in (("encoder", model.encoder), ("generator", model.generator),
                                         ("discriminator", dis)) for k in m.state_dict() if "running" in k]
    losses = {f"loss.{k}" for k in ("d", "e", "g", "gan", "feature", "pixel_l1", "kl")}
    assert set(got) == losses | {f"grad.{p}" for p in params} | set(params) | set(stats)
    assert got["grad.discriminator.out.weight"].shape == (1, CFG.flat)


def test_vae_gan_step_needs_a_discriminator(tmp_path, capsys):
    weights, batch = gan_files(tmp_path, with_discriminator=False)
    with pytest.raises(SystemExit) as exit:
        train.main(["step", "--stage", "vae-gan", "--weights", str(weights), "--batch", str(batch),
                    "--out", str(tmp_path / "o.safetensors")])
    assert exit.value.code == 2 and "discriminator" in capsys.readouterr().err


def test_vae_gan_encoder_gradient_is_its_losss_derivative():
    # The encoder's gradient is d(loss_e)/d(encoder), with the GAN term absent: checked by
    # central differences of loss_e in float64 along a random direction.
    torch.manual_seed(5)
    model, dis = DriveSim(CFG).double().train(), Discriminator(CFG).double().train()
    g = torch.Generator().manual_seed(6)
    x = torch.rand(3, CFG.channels, CFG.height, CFG.width, generator=g, dtype=torch.float64) * 2 - 1
    eps, prior = (torch.randn(3, CFG.z_dim, generator=g, dtype=torch.float64) for _ in range(2))
    state = {k: v.clone() for k, v in model.state_dict().items()}
    dstate = {k: v.clone() for k, v in dis.state_dict().items()}
    opts = [torch.optim.SGD(m.parameters(), lr=0.0) for m in (model.encoder, model.generator, dis)]
    losses, grads, _ = vae_gan_step(model.encoder, model.generator, dis, opts, x, eps, prior)

    def loss_e(params):
        """loss_e with the encoder's parameters `params`, everything else as at the start."""
        model.load_state_dict(state)
        dis.load_state_dict(dstate)
        with torch.no_grad():
            for p, v in zip(model.encoder.parameters(), params):
                p.copy_(v)
        zero = [torch.optim.SGD(m.parameters(), lr=0.0) for m in (model.encoder, model.generator, dis)]
        return vae_gan_step(model.encoder, model.generator, dis, zero, x, eps, prior)[0]["e"]

    base = [p.detach().clone() for p in model.encoder.parameters()]
    direction = [torch.randn_like(p) for p in base]
    h = 1e-6
    up = loss_e([p + h * d for p, d in zip(base, direction)])
    down = loss_e([p - h * d for p, d in zip(base, direction)])
    numeric = (up - down) / (2 * h)
    analytic = sum((gr * d).sum() for gr, d in zip(grads["encoder"], direction))
    assert abs(numeric - analytic) <= 1e-5 * max(1.0, abs(float(numeric))), (float(numeric), float(analytic))


def torchrun(*args):
    """train.py ARGS in two processes on the CPU (gloo), as torchrun runs it on several GPUs."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m", "drivesim_reference.train", *args]
    done = subprocess.run(cmd, cwd=HERE, env=dict(os.environ, OMP_NUM_THREADS="1"), capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]


def relative(a, b):
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))


def test_two_processes_take_the_step_of_one(tmp_path):
    # Each process takes half the batch; BatchNorm's statistics and the feature error's variance
    # are the global batch's and the gradients are averaged: the step of one process on all of it.
    weights, batch = gan_files(tmp_path)
    one, two = tmp_path / "one.safetensors", tmp_path / "two.safetensors"
    args = ["step", "--stage", "vae-gan", "--weights", str(weights), "--batch", str(batch), "--lr", "0"]
    train.main(args + ["--out", str(one)])
    torchrun(*args, "--out", str(two))
    a, b = load_file(str(one)), load_file(str(two))
    assert set(a) == set(b)
    for name in a:
        # The gradient of a convolution's bias before BatchNorm is zero up to rounding.
        before_bn = name.startswith("grad.") and name.endswith(".bias") and any(
            name.endswith(f"{layer}.bias") for layer in ("conv1", "conv2", "conv3", "convs.1", "convs.2", "convs.3",
                                                        "deconv1", "deconv2", "deconv3"))
        if not before_bn:
            assert relative(b[name], a[name]) <= 1e-4, name


def test_fit_on_two_processes_is_fit_on_one(tmp_path, tiny_episodes):
    args = ["fit", "--data", str(tiny_episodes), "--device", "cpu", "--base-channels", "2", "--z-dim", "4", "--hidden-dim", "6",
            "--vae-steps", "3", "--batch", "4", "--transition-steps", "3", "--transition-batch", "4",
            "--lr", "1e-6", "--transition-lr", "1e-6", "--log-every", "1", "--dtype", "f32"]
    one, two = tmp_path / "one.safetensors", tmp_path / "two.safetensors"
    train.main(args + ["--out", str(one)])
    torchrun(*args, "--out", str(two))
    a, b = load_file(str(one)), load_file(str(two))
    assert set(a) == set(b)
    for name in a:
        assert relative(b[name], a[name]) <= 1e-4, name

"""The transition training step: weights/tool -m pytest test_train.py"""

import pytest
import torch
from safetensors.torch import load_file, save_file

import train
from model import Config, DriveSim, save_drivesim

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
    _, grads = train.transition_step(tr, opt, z, c, teacher=2, clip=1e9, detach=False)
    eps = 1e-6
    for name, p in tr.named_parameters():
        direction = torch.randn_like(p)
        with torch.no_grad():
            p += eps * direction
            up = torch.nn.functional.mse_loss(train.predict(tr, z, c, 2), z[:, 1:])
            p -= 2 * eps * direction
            down = torch.nn.functional.mse_loss(train.predict(tr, z, c, 2), z[:, 1:])
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
        results.append(train.transition_step(tr, opt, z, c, teacher=4, clip=1e9, detach=detach)[1])
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

"""The heads' reference training (heads.py) and the heads in the weight format (model.py):
weights/tool -m pytest test_heads.py"""

import json

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from heads import HeadTrainer, lambda_returns, train_step
from model import DISCOUNT_KEY, Config, DriveSim, Head, Policy, from_state_dict, load_drivesim, save_drivesim

CFG = Config(16, 32, 2, 3, z_dim=5, hidden_dim=7, action_dim=3)


def test_lambda_returns_by_hand():
    # The crate's doctest: λ = 1 with zero values is the discounted sum of the rewards.
    assert lambda_returns([1.0, 1.0, 1.0], [0.0, 0.0, 0.0], 0.5, 1.0).tolist() == [1.75, 1.5, 1.0]
    r, v = [1.0, 2.0, 3.0], [10.0, 20.0, 30.0]
    # λ = 0: the one-step TD targets r_t + γ v_{t+1}.
    assert lambda_returns(r, v, 0.5, 0.0).tolist() == [6.0, 12.0, 18.0]
    # λ = 1: the rewards to the end plus γ^(T-t) v_T; the values between are not read.
    assert lambda_returns(r, v, 0.5, 1.0).tolist() == [6.5, 11.0, 18.0]
    assert lambda_returns(r, [-7.0, 99.0, 30.0], 0.5, 1.0).tolist() == [6.5, 11.0, 18.0]
    # Between: G_1 = 2 + .5 (.5 * 8 + .5 * 8) = 6, G_0 = 1 + .5 (.5 * 4 + .5 * 6) = 3.5.
    assert lambda_returns([1.0, 2.0], [4.0, 8.0], 0.5, 0.5).tolist() == [3.5, 6.0]
    # A drive that ended for good (v_T = 0) and one decision.
    assert lambda_returns([2.0], [0.0], 0.9, 0.8).tolist() == [2.0]
    assert lambda_returns([], [], 0.9, 0.8).tolist() == []


def test_lambda_returns_in_float32_and_torch():
    rng = np.random.default_rng(0)
    r, v = rng.normal(size=50), rng.normal(size=50) * 3
    got = lambda_returns(r, v, 0.97, 0.9)
    assert got.dtype == np.float32
    exact, g = np.empty(50), v[-1]
    for t in range(49, -1, -1):
        g = exact[t] = r[t] + 0.97 * (0.1 * v[t] + 0.9 * g)
    np.testing.assert_allclose(got, exact, rtol=1e-5, atol=1e-5)
    as_torch = lambda_returns(torch.tensor(r, dtype=torch.float32), torch.tensor(v), 0.97, 0.9)
    assert isinstance(as_torch, torch.Tensor) and np.array_equal(as_torch.numpy(), got)


@pytest.mark.parametrize("args, match", [
    (([1.0], [0.0], 1.5, 0.5), "discount"),
    (([1.0], [0.0], 0.5, -0.1), "lambda"),
    (([1.0, 2.0], [0.0], 0.5, 0.5), "next values"),
    (([float("nan")], [0.0], 0.5, 0.5), "finite"),
])
def test_lambda_returns_refuses_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        lambda_returns(*args)


def batch(n, generator):
    return torch.randn(n, CFG.z_dim, generator=generator), torch.rand(n, CFG.hidden_dim, generator=generator) * 2 - 1


def test_the_loss_is_in_the_units_and_the_start_is_the_head():
    torch.manual_seed(1)
    head = Head(CFG, 6, "reward")
    units = [(1.5, 2.0), (0.3, 0.45)]
    trainer = HeadTrainer(head, units)
    for name, value in trainer.tensors().items():
        assert name.startswith("reward.")
        torch.testing.assert_close(value, head.state_dict()[name.removeprefix("reward.")], rtol=1e-6, atol=1e-7)
    z, h = batch(9, torch.Generator().manual_seed(2))
    y = torch.randn(9, 2)
    with torch.no_grad():
        expected = (((head(z, h) - y) / torch.tensor([2.0, 0.45])) ** 2).mean().item()
    assert trainer.loss(torch.cat([z, h], 1), y) == pytest.approx(expected, rel=1e-5)
    before = [p.detach().clone() for p in trainer.params]
    loss = trainer.step(torch.cat([z, h], 1), y, 0.01)
    assert loss == pytest.approx(expected, rel=1e-5) and trainer.steps == 1
    # Adam's first step moves every scaled parameter by about lr (its gradient's sign).
    moved = torch.cat([(p.detach() - b).abs().flatten() for p, b in zip(trainer.params, before)])
    assert moved.max() <= 0.01 * (1 + 1e-4) and moved.median() > 0.009
    # The head itself holds the unscaled tensors after the step.
    for name, value in trainer.tensors().items():
        assert torch.equal(head.state_dict()[name.removeprefix("reward.")], value)


def test_steps_fit_a_learnable_target():
    """A value head learns another head's outputs (in units far from its own): the loss falls
    tenfold; train_step keeps Adam's state on the head between calls."""
    torch.manual_seed(3)
    teacher, student = Head(CFG, 7, "value"), Head(CFG, 7, "value")
    z, h = batch(32, torch.Generator().manual_seed(4))
    with torch.no_grad():
        targets = 5.0 + 3.0 * teacher(z, h)
    units = [(5.0, 3.0)]
    inputs = torch.cat([z, h], 1)
    losses = [train_step(student, units, inputs, targets, 0.01) for _ in range(300)]
    assert student._trainer.steps == 300
    assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])
    with torch.no_grad():
        assert (((student(z, h) - targets) / 3.0) ** 2).mean().item() < 0.1 * losses[0]
    # Other units: a new trainer from the head as it is.
    train_step(student, [(0.0, 1.0)], inputs, targets, 0.01)
    assert student._trainer.steps == 1


def test_the_trainer_refuses_bad_units():
    head = Head(CFG, 4, "reward")
    with pytest.raises(ValueError, match="units"):
        HeadTrainer(head, [(0.0, 1.0)])
    with pytest.raises(ValueError, match="deviations"):
        HeadTrainer(head, [(0.0, 1.0), (0.0, 0.0)])


def test_the_heads_round_trip_through_the_loader(tmp_path):
    torch.manual_seed(5)
    full = DriveSim(CFG, policy_width=4, reward_width=5, value_width=3, discount=0.95).eval()
    assert isinstance(full.policy, Policy) and isinstance(full.policy, Head)
    assert [(k, h.prefix, h.width, h.outputs) for k, h in full.heads().items()] == [
        ("policy", "policy.", 4, 3), ("reward", "reward.", 5, 2), ("value", "value.", 3, 1)]
    path = tmp_path / "heads.safetensors"
    save_drivesim(full, CFG, path)
    with safe_open(str(path), "pt") as f:
        assert f.metadata()[DISCOUNT_KEY] == "0.95"
        assert {"reward.output.weight", "value.output.bias"} <= set(f.keys())
        assert list(f.get_tensor("reward.hidden.weight").shape) == [5, CFG.z_dim + CFG.hidden_dim]
    loaded, cfg = load_drivesim(path)
    assert cfg == CFG and loaded.discount == 0.95
    assert loaded.state_dict().keys() == full.state_dict().keys()
    for name, value in full.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name
    z, h = torch.randn(2, CFG.z_dim), torch.randn(2, CFG.hidden_dim)
    assert torch.equal(loaded.value(z, h), full.value(z, h)) and loaded.reward(z, h).shape == (2, 2)
    # A load and a save keep the discount (export.py's round trip); a file without one has none.
    again = tmp_path / "again.safetensors"
    save_drivesim(loaded, CFG, again)
    assert load_file(str(again)).keys() == load_file(str(path)).keys()
    with safe_open(str(again), "pt") as f:
        assert json.loads(f.metadata()["drivesim.config"]) == json.loads(CFG.to_json())
        assert f.metadata()[DISCOUNT_KEY] == "0.95"
    reward_only = DriveSim(CFG, reward_width=2)
    save_drivesim(reward_only, CFG, path, "f16")
    loaded, _ = load_drivesim(path)
    assert loaded.reward.width == 2 and not hasattr(loaded, "value") and not hasattr(loaded, "policy")
    assert loaded.discount is None and list(loaded.heads()) == ["reward"]


def test_a_head_missing_a_tensor_or_a_bad_discount_is_refused(tmp_path):
    tensors = {k: v.clone() for k, v in DriveSim(CFG, value_width=3).state_dict().items()
               if not k.endswith("num_batches_tracked")}
    del tensors["value.output.bias"]
    with pytest.raises(ValueError, match="value.output.bias"):
        from_state_dict(CFG, tensors)
    del tensors["value.hidden.bias"]
    with pytest.raises(ValueError, match="value.hidden.bias"):
        from_state_dict(CFG, tensors)
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="discount"):
            DriveSim(CFG, discount=bad)
    path = tmp_path / "bad.safetensors"
    save_drivesim(DriveSim(CFG), CFG, path)
    meta = {"drivesim.config": CFG.to_json(), DISCOUNT_KEY: "1.5"}
    save_file(load_file(str(path)), str(path), metadata=meta)
    with pytest.raises(ValueError, match="discount"):
        load_drivesim(path)


def test_the_committed_heads_fixture_is_reproduced(tmp_path):
    """tests/fixtures/heads_f32.train.safetensors, regenerated (fixtures.py --check's test, for
    this fixture alone: a second)."""
    import fixtures

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fixtures.reference_heads(tmp_path)
    finally:
        torch.set_num_threads(threads)
    name = "heads_f32.train.safetensors"
    assert fixtures.compare(fixtures.OUT / name, tmp_path / name) == []

"""The heads' reference training (heads.py) and the heads in the weight format (model.py):
weights/tool -m pytest tests/test_heads.py"""

import json

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from drivesim_reference.heads import HeadTrainer, lambda_returns, train_step
from drivesim_reference.model import DISCOUNT_KEY, Config, DriveSim, Head, Policy, from_state_dict, load_drivesim, save_drivesim

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
    full = DriveSim(CFG, policy_width=4, reward_width=5, value_width=3, discount=0.95, pace_width=2).eval()
    assert isinstance(full.policy, Policy) and isinstance(full.policy, Head)
    assert [(k, h.prefix, h.width, h.outputs) for k, h in full.heads().items()] == [
        ("policy", "policy.", 4, 3), ("reward", "reward.", 5, 2), ("value", "value.", 3, 1), ("pace", "pace.", 2, 1)]
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
    assert torch.equal(loaded.pace(z, h), full.pace(z, h))
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
    from drivesim_reference import fixtures

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fixtures.reference_heads(tmp_path)
    finally:
        torch.set_num_threads(threads)
    name = "heads_f32.train.safetensors"
    assert fixtures.compare(fixtures.OUT / name, tmp_path / name) == []


# `train.py heads` (train_heads.py): the Rust `train heads`'s twin, on tiny files.

HEAD_CFG = Config(16, 32, 3, 2, z_dim=4, hidden_dim=6, action_dim=2)
ACTIONS = [dict(name="speed", unit="m/s", mean=1.0, std=2.0, min=-3.0, max=4.0),
           dict(name="steering", unit="as recorded", mean=0.0, std=0.5, min=-1.0, max=1.0)]


def reward_episodes(path, lengths=(6, 8, 10), seed=0, rewards=True):
    """Episodes of random 16x32 frames, with random rewards (or none)."""
    from drivesim import episodes

    rng = np.random.default_rng(seed)
    n = sum(lengths)
    frames = rng.integers(0, 256, (n, 16, 32, 3), dtype=np.uint8)
    actions = rng.normal(size=(n, 2)).astype(np.float32)
    outcomes = dict(reward=rng.normal(size=n).astype(np.float32), tiles=rng.integers(0, 3, n).astype(np.int32),
                    on_road=rng.integers(0, 2, n).astype(np.uint8)) if rewards else None
    episodes.write(path, episodes.Episodes(frames, actions, np.cumsum([0, *lengths[:-1]]), outcomes))
    return path


@pytest.fixture
def head_files(tmp_path):
    """An f16 weight file with a policy, action metadata, a frame rate and a discriminator, and
    three episodes (6, 8 and 10 frames) with rewards."""
    from drivesim_reference.vae_gan import Discriminator

    torch.manual_seed(11)
    weights = tmp_path / "w.safetensors"
    save_drivesim(DriveSim(HEAD_CFG, policy_width=3), HEAD_CFG, weights, "f16", actions=ACTIONS,
                  discriminator=Discriminator(HEAD_CFG), frame_hz=12.5)
    return weights, reward_episodes(tmp_path / "e.safetensors")


def run_heads(capsys, weights, data, out, *more):
    from drivesim_reference import train

    train.main(["heads", "--weights", str(weights), "--episodes", str(data), "--out", str(out), "--steps", "12",
                "--batch", "5", "--width", "3", "--refresh", "5", *more])
    return capsys.readouterr().out


def assert_the_rest_is_kept(original, written, head):
    """Every tensor but the head's as it was (dtype included), the metadata the same but the
    discount."""
    a, b = load_file(str(original)), load_file(str(written))
    assert {k for k in b if not k.startswith(head + ".")} == {k for k in a if not k.startswith(head + ".")}
    for name, value in a.items():
        if not name.startswith(head + "."):
            assert b[name].dtype == value.dtype and torch.equal(b[name], value), name
    with safe_open(str(original), "pt") as f, safe_open(str(written), "pt") as g:
        before, after = f.metadata(), g.metadata()
    if head == "value":
        before.pop(DISCOUNT_KEY, None)
        after.pop(DISCOUNT_KEY)
    assert {k: json.loads(v) for k, v in after.items()} == {k: json.loads(v) for k, v in before.items()}


def test_heads_command_trains_both_heads_into_the_file(head_files, tmp_path, capsys):
    weights, data = head_files
    reward, value = tmp_path / "reward.safetensors", tmp_path / "value.safetensors"
    text = run_heads(capsys, weights, data, reward, "--head", "reward")
    # Two episodes (5 + 7 decisions) and their mirror images train, the third's two views are held out.
    assert "24 examples (18 held out), reward head width 3" in text and "wrote" in text
    assert "held out, before" not in text and "held out, after: RMS error reward" in text
    loaded, cfg = load_drivesim(reward)
    assert cfg == HEAD_CFG and list(loaded.heads()) == ["policy", "reward"] and loaded.reward.width == 3
    assert loaded.discount is None and load_file(str(reward))["reward.output.weight"].dtype == torch.float16
    assert_the_rest_is_kept(weights, reward, "reward")
    heldout = reward_episodes(tmp_path / "h.safetensors", lengths=(4, 5), seed=1)
    text = run_heads(capsys, reward, data, value, "--head", "value", "--discount", "0.9", "--lambda", "0.8",
                     "--heldout", str(heldout), "--no-mirror", "--width", "2")
    assert "21 examples (7 held out), value head width 2" in text and "λ-returns" in text
    loaded, _ = load_drivesim(value)
    assert list(loaded.heads()) == ["policy", "reward", "value"] and loaded.discount == 0.9
    with safe_open(str(value), "pt") as f:
        assert f.metadata()[DISCOUNT_KEY] == "0.9"
    assert_the_rest_is_kept(reward, value, "value")
    # A head the file has goes on training (its own width), reported before and after; --restart
    # draws a new one of --width.
    again = tmp_path / "again.safetensors"
    text = run_heads(capsys, value, data, again, "--head", "value", "--width", "5")
    assert "value head width 2" in text and "held out, before" in text and "held out, after" in text
    assert load_drivesim(again)[0].discount == 0.98
    text = run_heads(capsys, value, data, again, "--head", "reward", "--width", "5", "--restart")
    assert "reward head width 5" in text and "held out, before" in text
    assert load_drivesim(again)[0].discount == 0.9  # the file's, kept by the reward head's run


def test_heads_command_is_seeded(head_files, tmp_path, capsys):
    weights, data = head_files
    one, two, other = (tmp_path / f"{n}.safetensors" for n in ("one", "two", "other"))
    for out in (one, two):
        run_heads(capsys, weights, data, out, "--head", "value", "--seed", "3")
    run_heads(capsys, weights, data, other, "--head", "value", "--seed", "4")
    assert one.read_bytes() == two.read_bytes() != other.read_bytes()


def test_heads_command_refuses_episodes_without_rewards(head_files, tmp_path, capsys):
    from drivesim_reference import train

    weights, data = head_files
    bare = reward_episodes(tmp_path / "bare.safetensors", rewards=False)
    for more in (["--episodes", str(bare)], ["--episodes", str(data), "--heldout", str(bare)]):
        with pytest.raises(SystemExit) as exit:
            train.main(["heads", "--weights", str(weights), "--out", str(tmp_path / "o.safetensors"),
                        "--head", "reward", "--width", "3", *more])
        err = capsys.readouterr().err
        assert exit.value.code == 2 and "without rewards (`reward`, `on_road`)" in err and str(bare) in err
    assert not (tmp_path / "o.safetensors").exists()
    with pytest.raises(SystemExit) as exit:
        train.main(["heads", "--weights", str(weights), "--out", str(tmp_path / "o.safetensors"),
                    "--head", "value", "--episodes", str(data), "--holdout", "3", "--width", "3"])
    assert exit.value.code == 2 and "--holdout 3 leaves no training episode" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit:  # the crate reads no head wider than hidden_dim
        train.main(["heads", "--weights", str(weights), "--out", str(tmp_path / "o.safetensors"),
                    "--head", "value", "--episodes", str(data), "--width", "7"])
    assert exit.value.code == 2 and "from 1 to the model's hidden_dim (6)" in capsys.readouterr().err


def test_the_examples_are_the_states_along_each_drive(head_files):
    from drivesim import episodes
    from drivesim_reference import train_heads

    weights, data = head_files
    model, cfg = load_drivesim(weights)
    drives = train_heads.views(model, episodes.read(data), no_mirror=False)
    assert len(drives) == 6 and [len(d[0]) for d in drives] == [6, 8, 10] * 2
    assert torch.equal(drives[3][1][:, 1], -drives[0][1][:, 1]) and torch.equal(drives[3][2], drives[0][2])
    frames = torch.from_numpy(episodes.read(data).frames[:6].copy())
    with torch.no_grad():
        assert torch.allclose(drives[3][0], model.encoder(train_heads.to_input(frames.flip(2)))[0], atol=1e-6)
    ex = train_heads.examples(model, cfg, drives[:2], 0.9, 0.8)
    codes, actions, reward, on_road = drives[1]
    h, rows = torch.zeros(cfg.hidden_dim), []
    with torch.no_grad():
        for t in range(8):
            rows.append(torch.cat([codes[t], h]))
            h = model.transition(codes[t], h, actions[t])[1]
    s = torch.stack(rows)
    assert ex.drive_ends == [5, 12] and len(ex.reward) == len(ex.value) == 12
    torch.testing.assert_close(ex.value.inputs[5:], s[:-1], rtol=0, atol=1e-6)
    torch.testing.assert_close(ex.reward.inputs[5:], s[1:], rtol=0, atol=1e-6)
    assert torch.equal(ex.reward.targets[5:, 0], reward[:-1])
    assert torch.equal(ex.reward.targets[5:, 1], 1.0 - on_road[1:].float())
    assert np.array_equal(ex.value.targets[5:, 0].numpy(), lambda_returns(reward[:-1].numpy(), np.zeros(7), 0.9, 0.8))
    next_values = torch.arange(12.0)
    ex.returns(next_values)
    assert np.array_equal(ex.value.targets[:5, 0].numpy(), lambda_returns(ex.rewards[:5], next_values[:5], 0.9, 0.8))
    units = ex.reward.units()
    t = ex.reward.targets.double()
    assert units[0] == pytest.approx((t[:, 0].mean().item(), t[:, 0].std(unbiased=False).item()), rel=1e-6)


def test_the_order_is_the_rust_commands():
    """Order's draws are examples/train/regression.rs's (its SplitMix64 shuffles, written out
    one by one here as in the Rust), across passes and batches that straddle them."""
    from drivesim_reference import train_heads

    mask = (1 << 64) - 1

    def rust_order(count, seed, draws):
        order, state, out = list(range(count)), seed, []
        while len(out) < draws:
            for i in range(count - 1, 0, -1):
                state = (state + 0x9E3779B97F4A7C15) & mask
                x = state
                x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
                x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
                j = (x ^ (x >> 31)) % (i + 1)
                order[i], order[j] = order[j], order[i]
            out += order
        return out[:draws]

    for count, seed, batch in ((7, 0, 3), (10, 2**64 - 5, 4), (1, 9, 2), (33, 12345, 33)):
        order = train_heads.Order(count, seed)
        got = np.concatenate([order.draw(batch) for _ in range(9)]).tolist()
        assert got == rust_order(count, seed, 9 * batch), (count, seed)
    assert train_heads.cosine_lr(1e-3, 0, 10) == np.float32(1e-3) and train_heads.cosine_lr(1e-3, 10, 10) == 0.0


# --dream-steps: the value head also learns from dreamed drives (dreams.rs's twin).

@pytest.fixture
def dream_weights(tmp_path):
    """An f16 weight file that can dream: a spread head with a noise factor, a policy, a reward head."""
    torch.manual_seed(12)
    model = DriveSim(HEAD_CFG, spread=True, policy_width=3, reward_width=2)
    model.transition.set_noise_factor(torch.linalg.cholesky(0.5 * torch.eye(4) + 0.5))
    save_drivesim(model, HEAD_CFG, tmp_path / "dream.safetensors", "f16", actions=ACTIONS)
    return tmp_path / "dream.safetensors"


def test_heads_command_trains_the_value_on_dreams(head_files, dream_weights, tmp_path, capsys):
    _, data = head_files
    out = tmp_path / "value.safetensors"
    text = run_heads(capsys, dream_weights, data, out, "--head", "value", "--dream-steps", "3", "--dream-every", "2")
    # Training: the 6- and 8-frame drives and their mirror images, 28 states, a dream from every
    # second: 14 drives of 3 decisions after the 5 + 7 + 5 + 7 real decisions.
    assert "14 dreamed drives of 3 decisions from real states" in text
    assert "66 examples (18 held out), value head width 3" in text and "wrote" in text
    loaded, _ = load_drivesim(out)
    assert list(loaded.heads()) == ["policy", "reward", "value"] and loaded.discount == 0.98
    assert_the_rest_is_kept(dream_weights, out, "value")
    # The reward head ignores the flags.
    text = run_heads(capsys, dream_weights, data, out, "--head", "reward", "--dream-steps", "3")
    assert "dreamed" not in text and "24 examples" in text


def test_the_dreams_start_from_the_real_states_and_follow_on(head_files, dream_weights):
    from drivesim import episodes
    from drivesim_reference import train_heads

    model, cfg = load_drivesim(dream_weights)
    drives = train_heads.views(model, episodes.read(head_files[1]), no_mirror=False)[:2]
    ex = train_heads.examples(model, cfg, drives, 0.9, 0.8)
    assert len(ex.states) == len(ex.speeds) == 14 and torch.equal(ex.speeds[6:], drives[1][1][:, 0])
    ranges = train_heads.action_ranges({"drivesim.actions": json.dumps(ACTIONS)})
    d = train_heads.dream(model, cfg, ex.states, ex.speeds, 3, 2, 5, ranges)
    assert d.ends == [3 * k for k in range(1, 8)] and d.inputs.shape == d.next_states.shape == (21, 10)
    assert torch.equal(d.inputs[::3], ex.states[::2])  # step 0: the real states
    for k in range(7):  # each step's next state is the next step's state
        assert torch.equal(d.next_states[3 * k:3 * k + 2], d.inputs[3 * k + 1:3 * k + 3])
    zd = cfg.z_dim
    with torch.no_grad():
        torch.testing.assert_close(d.rewards, model.reward(d.next_states[:, :zd], d.next_states[:, zd:])[:, 0])
        # The first step: driven at the speedometer's speed, the policy's steering clipped.
        z, h = ex.states[::2, :zd], ex.states[::2, zd:]
        steer = model.policy(z, h)[:, 1].clamp(-1.0, 1.0)
        h1 = model.transition(z, h, torch.stack([ex.speeds[::2], steer], 1))[1]
    torch.testing.assert_close(d.next_states[::3, zd:], h1)
    # Sampled: a seed of its own, the same again.
    again, other = (train_heads.dream(model, cfg, ex.states, ex.speeds, 3, 2, s, ranges) for s in (5, 6))
    assert torch.equal(again.next_states, d.next_states) and not torch.equal(other.next_states, d.next_states)
    real, reward_inputs = len(ex.value), ex.reward.inputs
    ex.add(d)
    assert real == 12 and len(ex.value) == len(ex.rewards) == len(ex.next_states) == 12 + 21
    assert ex.drive_ends == [5, 12] + [12 + e for e in d.ends] and ex.reward.inputs is reward_inputs
    assert torch.equal(ex.value.inputs[12:], d.inputs) and torch.equal(ex.next_states[12:], d.next_states)
    # Each dream a drive cut off: its λ-returns bootstrapped from its last state's value.
    next_values = torch.arange(33.0)
    ex.returns(next_values)
    assert np.array_equal(ex.value.targets[15:18, 0].numpy(),
                          lambda_returns(d.rewards[3:6], next_values[15:18], 0.9, 0.8))


def test_dreams_are_refused_without_a_policy_a_reward_head_or_a_spread(head_files, tmp_path, capsys):
    from drivesim_reference import train
    from drivesim_reference import train_heads

    weights, data = head_files  # a policy, no reward head, no spread head
    for more, match in ((["--dream-steps", "2"], "need the model's policy and reward head"),
                        (["--dream-steps", "-1"], "--dream-steps must be at least 0"),
                        (["--dream-steps", "2", "--dream-every", "0"], "--dream-every at least 1")):
        with pytest.raises(SystemExit) as exit:
            train.main(["heads", "--weights", str(weights), "--out", str(tmp_path / "o.safetensors"),
                        "--head", "value", "--episodes", str(data), "--width", "3", *more])
        assert exit.value.code == 2 and match in capsys.readouterr().err
    assert not (tmp_path / "o.safetensors").exists()
    no_spread = DriveSim(HEAD_CFG, policy_width=3, reward_width=2)
    states = torch.zeros(3, HEAD_CFG.z_dim + HEAD_CFG.hidden_dim)
    with pytest.raises(ValueError, match="predicts no spread"):
        train_heads.dream(no_spread, HEAD_CFG, states, torch.zeros(3), 2, 1, 0)

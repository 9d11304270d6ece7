"""`train.py driver` (train_driver.py): a driver learnt by the gradient of the dream's own return.
The dream it learns in is the crate's (the same return, step for step, as the crate's simulator
gives the same drives), the written file is the world with the driver as its policy and the
clone's pace head left out, a run stopped after a checkpoint goes on to the same bytes, a look at a
driver (--look) reports what its rollout does, drivers' mean (--average) is the crate's policy and
the mean of their actions, and bad settings or a world without its heads are refused."""

import dataclasses
import json
import types

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from drivesim import episodes
from drivesim_reference.model import DriveSim, load_drivesim, save_drivesim
from drivesim_reference.train_driver import DreamDriver, real_states, speed_after
from test_heads import ACTIONS, HEAD_CFG, reward_episodes
from test_texture import assert_resumes_to_the_same_bytes

DRIVER = [f"policy.{l}.{p}" for l in ("hidden", "output") for p in ("bias", "weight")]


def run(weights, data, out, *more):
    from drivesim_reference import train

    train.main(["driver", "--weights", str(weights), "--episodes", str(data), "--out", str(out), "--steps", "6",
                "--batch", "5", "--horizon", "4", "--width", "3", "--lr", "1e-2", "--top-speed", "4",
                "--first-speed", "3", "--value", *more])


def world(path, **heads):
    torch.manual_seed(2)
    model = DriveSim(HEAD_CFG, **{"policy_width": 3, "reward_width": 4, "value_width": 3, "discount": 0.9,
                                  "texture_width": 4, "pace_width": 2, **heads})
    save_drivesim(model, HEAD_CFG, path, "f32", actions=ACTIONS, frame_hz=12.5, discount=model.discount)
    return path


def settings(**changes):
    """The trainer's arguments for the tests that step it directly: a small driver in the mean
    dream with every guard off, but for `changes`."""
    base = dict(from_policy=False, width=3, first_speed=3.0, lr=1e-3, horizon=4, top_speed=4.0, temperature=0.0,
                off_road_cost=0.0, value=False, steer_gain=(1.0, 1.0), lateral_cost=0.0, lateral_limit=0.2,
                lateral_by="both", brake_gradient=False)
    return types.SimpleNamespace(**{**base, **changes})


@pytest.fixture
def files(tmp_path):
    return world(tmp_path / "w.safetensors"), reward_episodes(tmp_path / "e.safetensors", lengths=(15, 17))


def test_the_driver_replaces_the_policy_drops_the_pace_head_and_resumes_to_the_same_bytes(tmp_path, files):
    weights, data = files
    run(weights, data, tmp_path / "whole.safetensors")
    before, after = load_file(str(weights)), load_file(str(tmp_path / "whole.safetensors"))
    assert set(before) - set(after) == {k for k in before if k.startswith("pace.")}
    assert sorted(k for k in after if k.startswith("policy.")) == DRIVER
    assert after["policy.hidden.weight"].shape == (3, HEAD_CFG.z_dim + HEAD_CFG.hidden_dim)
    assert after["policy.output.weight"].abs().max() > 0, "the driver learnt from its zero output layer"
    kept = {k for k in before if not k.startswith(("policy.", "pace."))}
    assert all(torch.equal(after[k], before[k]) for k in kept)
    assert_resumes_to_the_same_bytes(run, weights, data, tmp_path, "--horizon", "3", "--steer-gain", "1,2")


@pytest.mark.parametrize("gain", [1.0, 1.7])
def test_the_dream_it_learns_in_is_the_crates(tmp_path, files, gain):
    """At temperature 0 the trainer's return of a drive is what the crate's simulator gives for
    the same actions: its transition, speed response, reward, off-road chance, discount, value and
    the lateral load's cost;
    with a steering gain (--steer-gain 1.7,1.7), the crate's transition stepped with the steering
    times the gain (and --brake-gradient, which changes no number the dream gives)."""
    from drivesim import Model, Simulator
    from drivesim.carracing.control import speed_after as crate_speed_after

    weights, _ = files
    model, cfg = load_drivesim(weights)
    args = settings(horizon=5, off_road_cost=0.5, value=True, steer_gain=(gain, gain), lateral_cost=50.0,
                    lateral_limit=0.001, brake_gradient=gain != 1.0)
    torch.manual_seed(0)
    trainer = DreamDriver(model, cfg, args)
    torch.nn.init.normal_(trainer.driver.output.weight)  # a driver that steers and changes its speed
    rng = np.random.default_rng(1)
    z = rng.standard_normal((3, cfg.z_dim)).astype(np.float32)
    h = rng.uniform(-0.5, 0.5, (3, cfg.hidden_dim)).astype(np.float32)
    speed = np.array([1.0, 2.5, 3.5], np.float32)
    with torch.no_grad():
        total, off, _, _ = trainer.rollout(torch.from_numpy(z), torch.from_numpy(h), torch.from_numpy(speed))
    sim = Simulator(Model.load(str(weights)), batch=3)
    expected, off_sum, weight = np.zeros(3), np.zeros(3), 1.0
    for _ in range(args.horizon):
        with torch.no_grad():
            out = trainer.driver(torch.from_numpy(z), torch.from_numpy(h)).numpy()
        target, steer = np.clip(out[:, 0], 2.0, 4.0), np.clip(out[:, 1], -1.0, 1.0)
        lateral = np.maximum((speed / 50.0) ** 2 * np.abs(steer) - 0.001, 0.0)
        z, h = sim.transition(z, h, np.stack([speed, gain * steer], 1).astype(np.float32))
        speed = crate_speed_after(speed, target).astype(np.float32)
        reward = sim.reward(z, h)
        expected += weight * (reward[:, 0] - 0.5 * reward[:, 1] - 50.0 * lateral)
        off_sum += reward[:, 1]
        weight *= 0.9
    expected += weight * sim.value(z, h)[:, 0]
    np.testing.assert_allclose(total.numpy(), expected, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(off.numpy(), off_sum / args.horizon, rtol=1e-4, atol=1e-5)
    assert torch.equal(speed_after(torch.tensor([10.0, 10.0, 10.0]), torch.tensor([30.0, 11.0, 4.0])),
                       torch.tensor([12.0, 10.2, 4.0]))


def test_the_brake_gradient_passes_the_dead_band_and_keeps_the_speed():
    """A target a little under the speed keeps it (the dead band) and passes no gradient back;
    with --brake-gradient the speed is the same and the gradient GAIN's, as a little above."""
    for straight_through, slope in ((False, 0.0), (True, 0.2)):
        target = torch.tensor([8.0, 11.0, 4.0], requires_grad=True)
        after = speed_after(torch.full((3,), 10.0), target, straight_through)
        after.sum().backward()
        assert torch.equal(after.detach(), torch.tensor([10.0, 10.2, 4.0]))
        assert torch.allclose(target.grad, torch.tensor([slope, 0.2, 1.0]))


def test_each_drive_draws_its_own_steering_gain(files):
    """--steer-gain LO,HI: two drives from the same state in the mean dream differ, each by its
    own gain (a run with the range resumes to the same bytes: the first test's)."""
    weights, _ = files
    model, cfg = load_drivesim(weights)
    args = settings(steer_gain=(1.0, 3.0))
    torch.manual_seed(0)
    trainer = DreamDriver(model, cfg, args)
    torch.nn.init.normal_(trainer.driver.output.weight)
    z, h = torch.randn(1, cfg.z_dim).repeat(2, 1), torch.zeros(2, cfg.hidden_dim)
    with torch.no_grad():
        total, _, _, _ = trainer.rollout(z, h, torch.full((2,), 2.0))
        args.steer_gain = (1.0, 1.0)
        same, _, _, _ = trainer.rollout(z, h, torch.full((2,), 2.0))
    assert total[0] != total[1] and same[0] == same[1]


def test_the_lateral_cost_by_speed_changes_the_speed_alone(files):
    """--lateral-by speed: the cost's gradient reaches the driver's speed output and not its
    steering's (over two decisions, where a steering reaches the cost only directly: later, it
    also changes the states the later speeds are chosen in); --lateral-by both reaches both."""
    weights, _ = files
    model, cfg = load_drivesim(weights)
    for p in model.parameters():
        p.requires_grad_(False)
    z, h = torch.randn(4, cfg.z_dim, generator=torch.Generator().manual_seed(3)), torch.zeros(4, cfg.hidden_dim)

    def gradient(cost, by):
        args = settings(horizon=2, lateral_cost=cost, lateral_limit=0.0, lateral_by=by)
        torch.manual_seed(0)
        trainer = DreamDriver(model, cfg, args)
        torch.nn.init.normal_(trainer.driver.output.weight)
        total, _, _, _ = trainer.rollout(z, h, torch.full((4,), 2.0))
        total.sum().backward()
        return trainer.driver.output.weight.grad

    free, by_speed, by_both = gradient(0.0, "speed"), gradient(1e4, "speed"), gradient(1e4, "both")
    assert torch.allclose(by_speed[1], free[1]) and not torch.allclose(by_speed[0], free[0])
    assert not torch.allclose(by_both[1], free[1])


def test_from_the_policy_it_starts_as_the_clone_stays_near_and_keeps_the_pace_head(tmp_path, files):
    """--from-policy: the first step's driver is the file's policy; --stay pays for moving away
    from it (a larger --stay moves less); the written file keeps the pace head."""
    weights, data = files
    moved = {}
    for stay in ("0", "1000"):
        out = tmp_path / f"ft{stay}.safetensors"
        run(weights, data, out, "--from-policy", "--stay", stay, "--width", "3")
        before, after = load_file(str(weights)), load_file(str(out))
        assert set(after) == set(before), "every tensor kept, the pace head among them"
        moved[stay] = sum(float((after[k] - before[k]).square().sum()) for k in DRIVER)
    assert 0 < moved["1000"] < moved["0"]
    model, cfg = load_drivesim(weights)
    args = settings(from_policy=True)
    trainer = DreamDriver(model, cfg, args)
    z, h = torch.randn(2, cfg.z_dim), torch.zeros(2, cfg.hidden_dim)
    assert torch.equal(trainer.driver(z, h), model.policy(z, h))


@pytest.mark.parametrize("bad", [["--lr", "0"], ["--horizon", "0"], ["--width", "0"], ["--temperature", "-1"],
                                 ["--top-speed", "1"], ["--first-speed", "9"], ["--off-road-cost", "nan"],
                                 ["--lateral-cost", "-1"], ["--lateral-limit", "-0.1"], ["--lateral-cost", "inf"],
                                 ["--lateral-by", "steering"], ["--stay", "1"],
                                 ["--from-policy", "--stay", "-1"],
                                 ["--steer-gain", "0,1"], ["--steer-gain", "2,1"], ["--steer-gain", "1,nan"],
                                 ["--steer-gain", "1,2,3"]])
def test_bad_settings_exit_with_a_message_and_write_nothing(tmp_path, files, bad):
    weights, data = files
    with pytest.raises(SystemExit):
        run(weights, data, tmp_path / "x.safetensors", *bad)
    assert not (tmp_path / "x.safetensors").exists()


def test_a_world_without_a_value_head_sums_its_rewards(tmp_path):
    """Without --value a world needs no value head, and with it no discount: the rewards are
    summed as dream-train sums them."""
    from drivesim_reference import train

    weights = world(tmp_path / "w.safetensors", value_width=None, discount=None)
    data = reward_episodes(tmp_path / "e.safetensors", lengths=(15,))
    train.main(["driver", "--weights", str(weights), "--episodes", str(data), "--out", str(tmp_path / "o.safetensors"),
                "--steps", "2", "--batch", "3", "--horizon", "3", "--width", "3", "--top-speed", "4",
                "--first-speed", "3"])
    assert sorted(k for k in load_file(str(tmp_path / "o.safetensors")) if k.startswith("policy.")) == DRIVER


@pytest.mark.parametrize("missing, message", [({"reward_width": None}, "reward head"),
                                              ({"value_width": None}, "value head"),
                                              ({"texture_width": None}, "texture net")])
def test_a_world_without_its_heads_is_refused(tmp_path, missing, message):
    weights = world(tmp_path / "w.safetensors", **missing)
    data = reward_episodes(tmp_path / "e.safetensors", lengths=(15,))
    with pytest.raises(SystemExit):
        run(weights, data, tmp_path / "x.safetensors")
    assert not (tmp_path / "x.safetensors").exists()


def test_from_the_policy_of_a_world_without_one_is_refused(tmp_path, capsys):
    weights = world(tmp_path / "w.safetensors", policy_width=None)
    data = reward_episodes(tmp_path / "e.safetensors", lengths=(15,))
    with pytest.raises(SystemExit):
        run(weights, data, tmp_path / "x.safetensors", "--from-policy")
    assert "--from-policy needs a weight file with a policy" in capsys.readouterr().err
    assert not (tmp_path / "x.safetensors").exists()


def test_a_look_at_a_driver_reports_what_it_does_in_the_dream_and_writes_nothing(tmp_path, files, capsys):
    """--look DRIVER: a driver that asks for the top speed and steers 0.5 everywhere is reported
    at the top speed, steering, never braking, at the return its own rollout gives; a file whose
    policy reads another [z, h] is refused; --look A,B reports each and names the one of least
    lateral load (one that steers 0.1 rather than 0.5)."""
    from drivesim_reference import train

    weights, data = files
    model, cfg = load_drivesim(weights)
    with torch.no_grad():
        model.policy.output.weight.zero_()
        model.policy.output.bias.copy_(torch.tensor([4.0, 0.5]))
    save_drivesim(model, cfg, tmp_path / "d.safetensors", "f32", actions=ACTIONS, frame_hz=12.5, discount=model.discount)
    look = ["driver", "--weights", str(weights), "--episodes", str(data), "--look", str(tmp_path / "d.safetensors"),
            "--batch", "7", "--horizon", "5", "--top-speed", "4", "--first-speed", "3", "--value", "--temperature", "0"]
    train.main(look)
    seen = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert seen["at_top_speed"] == 1.0 and seen["steering"] == 1.0 and seen["braking"] == 0.0
    assert np.isfinite(seen["dream_return"]) and 0 <= seen["off_road"] <= 1 and seen["speed"] > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.safetensors", "e.safetensors", "w.safetensors"]
    trainer = DreamDriver(model, cfg, settings(horizon=5, value=True), driver=model.policy)
    data_states = real_states(model, episodes.read(str(data)), False)
    torch.manual_seed(0)
    i = torch.randint(len(data_states["speed"]), (7,))
    with torch.no_grad():
        total, _, _, _ = trainer.rollout(data_states["z"][i], data_states["h"][i], data_states["speed"][i])
    assert seen["dream_return"] == round(float(total.mean()), 4), "the look's return is its rollout's"
    wider = dataclasses.replace(HEAD_CFG, hidden_dim=HEAD_CFG.hidden_dim + 1)
    save_drivesim(DriveSim(wider, policy_width=3), wider, tmp_path / "o.safetensors", "f32", actions=ACTIONS,
                  frame_hz=12.5)
    with pytest.raises(SystemExit):
        train.main(look[:6] + [str(tmp_path / "o.safetensors")] + look[7:])
    assert "a weight file whose policy reads this world's [z, h]" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # neither --look nor --out
        train.main(look[:5] + look[7:])
    assert "--out is needed" in capsys.readouterr().err
    with torch.no_grad():  # a driver that steers less: less lateral load, named the least of the two
        model.policy.output.bias.copy_(torch.tensor([4.0, 0.1]))
    save_drivesim(model, cfg, tmp_path / "gentle.safetensors", "f32", actions=ACTIONS, frame_hz=12.5,
                  discount=model.discount)
    both = f"{tmp_path / 'd.safetensors'},{tmp_path / 'gentle.safetensors'}"
    train.main(look[:6] + [both] + look[7:] + ["--lateral-limit", "0"])
    lines = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()[-3:]]
    assert [line["driver"] for line in lines[:2]] == both.split(",")
    assert lines[0]["lateral_excess"] > lines[1]["lateral_excess"] > 0
    assert lines[2] == {"least_lateral_load": str(tmp_path / "gentle.safetensors")}


def test_the_mean_of_drivers_is_one_policy_the_crate_drives_at_their_mean_action(tmp_path, files, capsys):
    """--average A,B: the world of --weights (its pace head left out) with one policy as wide as
    both, whose action in the crate is the mean of theirs at any [z, h]; a driver of another
    world, a fine-tuned clone (it keeps the pace head), one driver alone, or drivers wider together
    than hidden_dim are refused and nothing is written."""
    from drivesim import Model, Simulator
    from drivesim_reference import train

    weights, data = files
    members = [tmp_path / "a.safetensors", tmp_path / "b.safetensors"]
    for seed, path in enumerate(members):
        run(weights, data, path, "--seed", str(seed))
    mean = tmp_path / "mean.safetensors"
    train.main(["driver", "--weights", str(weights), "--average", ",".join(map(str, members)), "--out", str(mean)])
    before, after = load_file(str(weights)), load_file(str(mean))
    assert after["policy.hidden.bias"].shape == (6,) and not any(k.startswith("pace.") for k in after)
    assert all(torch.equal(after[k], before[k]) for k in before if not k.startswith(("policy.", "pace.")))
    rng = np.random.default_rng(0)
    z = rng.normal(size=HEAD_CFG.z_dim).astype(np.float32)
    h = np.tanh(rng.normal(size=HEAD_CFG.hidden_dim)).astype(np.float32)
    acts = [Simulator(Model.load(str(path)), batch=1).act(z, h) for path in (*members, mean)]
    assert not np.allclose(acts[0], acts[1]), "two seeds learnt two drivers"
    np.testing.assert_allclose(acts[2], (acts[0] + acts[1]) / 2, rtol=1e-5, atol=1e-5)
    other = world(tmp_path / "other.safetensors")
    model, cfg = load_drivesim(other)
    with torch.no_grad():
        model.transition.W.add_(0.01)
    save_drivesim(model, cfg, other, "f32", actions=ACTIONS, frame_hz=12.5, discount=model.discount)
    run(other, data, tmp_path / "c.safetensors")
    run(weights, data, tmp_path / "clone.safetensors", "--from-policy")
    for bad, message in [([members[0], tmp_path / "c.safetensors"], "not a driver learnt afresh"),
                         ([members[0], tmp_path / "clone.safetensors"], "not a driver learnt afresh"),
                         ([members[0]], "two drivers or more"),
                         ([members[0]] * (HEAD_CFG.hidden_dim // 3 + 1), "at most the model's hidden_dim")]:
        with pytest.raises(SystemExit):
            train.main(["driver", "--weights", str(weights), "--average", ",".join(map(str, bad)),
                        "--out", str(tmp_path / "x.safetensors")])
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x.safetensors").exists()

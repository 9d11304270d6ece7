"""`train.py road` (train_road.py): the texture net fine-tuned so that the made-up roads bend as the
real ones do. It trains the texture net alone, writes the seed whose dream fits the training
family best, goes on after a kill to the same bytes, starts from a sampler file the crate accepts
for the world, refuses what it cannot use, and its road term compares what the docstring says."""

import json
import math

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from drivesim.carracing import failures
from drivesim_reference import train_road
from drivesim_reference.model import DriveSim, save_drivesim
from test_heads import ACTIONS, HEAD_CFG
from test_latent import TEXTURE

DRIVERS = len(failures.training_family())


def windows_folder(folder, seeds=(5, 6), length=80):
    """What `rank --family learnt --windows --out folder` keeps, random: each track's behaviour
    drive (codes, the clone's memory, speeds, steering) and every driver's windows' flags."""
    rng = np.random.default_rng(3)
    (folder / f"windows_{train_road.HORIZON}x{train_road.STARTS}").mkdir(parents=True)
    for seed in seeds:
        np.savez(folder / f"drive_{seed}.npz", z=rng.normal(size=(length, HEAD_CFG.z_dim)).astype(np.float32),
                 h=rng.normal(size=(length, HEAD_CFG.hidden_dim)).astype(np.float32),
                 speed=rng.uniform(1, 4, length).astype(np.float32),
                 steer=rng.uniform(-0.3, 0.3, length).astype(np.float32), first=np.int64(0))
        for i in range(DRIVERS):
            off = rng.integers(0, 2, (train_road.STARTS, train_road.HORIZON)).tolist()
            (folder / f"windows_{train_road.HORIZON}x{train_road.STARTS}" / f"learnt_{i}_{seed}.json").write_text(
                json.dumps({"driver": i, "seed": seed, "off": off}))
    return folder


def world(path, seed=1):
    torch.manual_seed(seed)
    save_drivesim(DriveSim(HEAD_CFG, policy_width=3, reward_width=3, texture_width=3), HEAD_CFG, path, "f32",
                  actions=ACTIONS, frame_hz=12.5)
    return path


def run(weights, windows, out, *more):
    from drivesim_reference import train

    train.main(["road", "--weights", str(weights), "--windows", str(windows), "--out", str(out), "--steps", "6",
                "--lr", "1e-2", "--log-every", "2", *more])


@pytest.fixture
def files(tmp_path):
    return world(tmp_path / "w.safetensors"), windows_folder(tmp_path / "rank")


def kept_seed(text):
    return int(text.split("kept seed ")[1].split()[0])


def test_it_trains_the_texture_net_alone_and_writes_the_best_fitting_seed(tmp_path, files, capsys):
    weights, windows = files
    run(weights, windows, tmp_path / "both.safetensors", "--seeds", "0,1")
    printed = capsys.readouterr().out
    fits = {s: float(printed.split(f"seed {s}: fit ")[1].split()[0]) for s in (0, 1)}
    assert kept_seed(printed) == min(fits, key=fits.get)
    before, after = load_file(str(weights)), load_file(str(tmp_path / "both.safetensors"))
    assert set(after) == set(before)
    assert all(torch.equal(after[k], v) for k, v in before.items() if k not in TEXTURE)
    assert all(not torch.equal(after[k], before[k]) for k in TEXTURE), "every tensor of the texture net learnt"
    run(weights, windows, tmp_path / "one.safetensors", "--seeds", str(kept_seed(printed)))
    assert (tmp_path / "one.safetensors").read_bytes() == (tmp_path / "both.safetensors").read_bytes()


def test_a_killed_run_goes_on_from_its_checkpoint_to_the_same_bytes(tmp_path, files, monkeypatch):
    weights, windows = files
    run(weights, windows, tmp_path / "whole.safetensors", "--seeds", "0,1")
    step, calls = train_road.RoadRun.step, []

    def killed(self, rows):
        calls.append(1)
        if len(calls) == 9:  # seed 1's third step: seed 0 done, a checkpoint of seed 1 after its second
            raise KeyboardInterrupt
        return step(self, rows)

    ckpt = ["--checkpoint", str(tmp_path / "run.ckpt"), "--checkpoint-every", "2"]
    monkeypatch.setattr(train_road.RoadRun, "step", killed)
    with pytest.raises(KeyboardInterrupt):
        run(weights, windows, tmp_path / "resumed.safetensors", "--seeds", "0,1", *ckpt)
    monkeypatch.setattr(train_road.RoadRun, "step", step)
    run(weights, windows, tmp_path / "resumed.safetensors", "--seeds", "0,1", *ckpt)
    assert (tmp_path / "resumed.safetensors").read_bytes() == (tmp_path / "whole.safetensors").read_bytes()
    with pytest.raises(SystemExit):  # another run's checkpoint
        run(weights, windows, tmp_path / "x.safetensors", "--seeds", "0,1", "--anchor", "1", *ckpt)
    assert not (tmp_path / "x.safetensors").exists()


def test_sampler_starts_from_a_sampler_file_of_this_world_and_refuses_another_worlds(tmp_path, files):
    from drivesim.sampler import write_sampler
    from drivesim.widen import widened_sampler

    weights, windows = files
    other = world(tmp_path / "other.safetensors", seed=2)  # another transition, another texture net
    same = load_file(str(weights))
    same.update({k: v for k, v in load_file(str(other)).items() if k in TEXTURE})
    retextured = tmp_path / "retextured.safetensors"  # this world with the other's texture net
    with safe_open(str(weights), "pt") as f:
        save_file(same, str(retextured), metadata=f.metadata())
    write_sampler(retextured, weights, tmp_path / "s.safetensors")
    run(weights, windows, tmp_path / "from.safetensors", "--sampler", str(tmp_path / "s.safetensors"),
        "--steps", "0")
    written = load_file(str(tmp_path / "from.safetensors"))
    assert all(torch.equal(written[k], same[k]) for k in TEXTURE)
    # A sampler with a read-out of its own (`python -m drivesim widen`) brings it along.
    centre = np.full(same["transition.a"].shape[0], 0.3)
    (tmp_path / "widened.safetensors").write_bytes(widened_sampler(tmp_path / "s.safetensors", weights, centre, 1.1))
    run(weights, windows, tmp_path / "wide.safetensors", "--sampler", str(tmp_path / "widened.safetensors"),
        "--steps", "0")
    written, wide = load_file(str(tmp_path / "wide.safetensors")), load_file(str(tmp_path / "widened.safetensors"))
    assert all(torch.equal(written[k], wide[k]) for k in (*TEXTURE, "transition.A", "transition.a"))
    assert not torch.equal(written["transition.a"], same["transition.a"])
    write_sampler(other, other, tmp_path / "o.safetensors")
    with pytest.raises(SystemExit):
        run(weights, windows, tmp_path / "x.safetensors", "--sampler", str(tmp_path / "o.safetensors"))
    assert not (tmp_path / "x.safetensors").exists()


@pytest.mark.parametrize("bad", [["--seeds", "x"], ["--seeds", "1,1"], ["--edges", "0"], ["--lr", "0"],
                                 ["--anchor", "nan"], ["--road-from", "40"], ["--windows", "nowhere"],
                                 ["--world-steering", "1.5,nan"], ["--world-steering", "1,2,3"]])
def test_what_it_cannot_use_exits_with_a_message(tmp_path, files, bad):
    weights, windows = files
    with pytest.raises(SystemExit):
        run(weights, windows, tmp_path / "x.safetensors", *bad)
    assert not (tmp_path / "x.safetensors").exists()


def test_a_world_without_a_texture_net_or_a_reward_head_is_refused(tmp_path, files, capsys):
    _, windows = files
    for name, widths in (("plain", dict(reward_width=3)), ("headless", dict(texture_width=3))):
        path = tmp_path / f"{name}.safetensors"
        save_drivesim(DriveSim(HEAD_CFG, policy_width=3, **widths), HEAD_CFG, path, "f32", actions=ACTIONS,
                      frame_hz=12.5)
        with pytest.raises(SystemExit):
            run(path, windows, tmp_path / "x.safetensors")
        assert "needs a texture net" in capsys.readouterr().err
        assert not (tmp_path / "x.safetensors").exists()


@pytest.mark.parametrize("damage", ["drive not an archive", "drive with NaN", "flags not 0 or 1", "flags not JSON"])
def test_a_damaged_file_in_the_windows_is_refused_naming_it(tmp_path, files, capsys, damage):
    weights, windows = files
    kept = windows / f"windows_{train_road.HORIZON}x{train_road.STARTS}" / "learnt_2_6.json"
    if damage == "drive not an archive":
        (windows / "drive_6.npz").write_bytes(b"not an archive")
    elif damage == "drive with NaN":
        with np.load(windows / "drive_6.npz") as f:
            drive = dict(f)
        drive["steer"][3] = np.nan
        np.savez(windows / "drive_6.npz", **drive)
    elif damage == "flags not 0 or 1":
        kept.write_text(json.dumps({"off": [[2] * 40] * train_road.STARTS}))
    else:
        kept.write_text("{")
    with pytest.raises(SystemExit):
        run(weights, windows, tmp_path / "x.safetensors")
    assert "track 6" in capsys.readouterr().err
    assert not (tmp_path / "x.safetensors").exists()


def test_windows_of_a_track_without_every_driver_are_left_out(tmp_path, files):
    weights, windows = files
    (windows / f"windows_{train_road.HORIZON}x{train_road.STARTS}" / "learnt_3_6.json").unlink()
    from drivesim_reference.model import load_drivesim

    model, cfg = load_drivesim(weights)
    data = train_road.load_windows(model, cfg, str(windows), (1.4, 0.0))
    assert data["tracks"] == 1 and data["off"].shape == (DRIVERS, train_road.STARTS, train_road.HORIZON)


def test_the_road_term_compares_the_mean_the_size_and_the_shares_past_the_view():
    class Args:
        road_from, edges, softness, shares = 10, [0.05], 0.02, 1.0

    term = train_road.RoadRun.road_term
    self = type("Run", (), {"args": Args})()
    real = torch.zeros(3, train_road.HORIZON)
    real[:, 10:] = 0.2  # a bend left past the view... as the dreamt clone steers it
    assert float(term(self, real.clone(), real)) == 0.0
    dreamt = real.clone()
    dreamt[:, :10] = -0.5  # what the view shows is not the road term's
    assert float(term(self, dreamt, real)) == 0.0
    straight = torch.zeros(3, train_road.HORIZON)  # made-up roads that do not bend: every term off
    assert float(term(self, straight, real)) > 1.0
    masked = real.clone()
    masked[0, 30:] = math.nan  # a drive ended: its decisions compare nothing
    dreamt = real.clone()
    dreamt[0, 30:] = 1.0
    assert float(term(self, dreamt, masked)) == 0.0


def test_the_worlds_steering_is_the_ranks_held_at_full_lock():
    """The dream trained in steps the world as `rank` does: the gain times the steering and a lead
    on its change, never past ±1; by default with the judge's settings."""
    from drivesim.carracing import rank, rank_dream

    steer, previous = np.float32([0.3, 0.9, -0.8, -0.5]), np.float32([0.1, 0.9, -0.8, 0.5])
    for shaping in [(1.4, 0.0), (1.5, 0.2)]:
        dreamt = train_road.steering_shaped(torch.from_numpy(steer), torch.from_numpy(previous), shaping)
        ranked = rank_dream.world_steering(np.stack([np.full(4, 50, np.float32), steer], 1), previous, shaping)
        np.testing.assert_allclose(dreamt.numpy(), ranked[:, 1], rtol=1e-6)
    np.testing.assert_allclose(dreamt.numpy(), [0.49, 1.0, -1.0, -0.95], rtol=1e-6)
    assert float(train_road.steering_shaped(np.float32(0.9), np.float32(0.0), (1.4, 0.0))) == 1.0  # a drive's
    parser = __import__("argparse").ArgumentParser()
    train_road.add_arguments(parser)
    assert parser.parse_args(["--weights", "w", "--windows", "d", "--out", "o"]).world_steering == rank.JUDGE_STEERING

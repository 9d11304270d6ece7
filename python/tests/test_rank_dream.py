"""The rank probe's dream (``drivesim.carracing.rank_dream``): the starts along a behaviour drive,
the dream batch, the drivers reading its frames, the open loop, the futures and the world's
steering shaped."""

import os

import numpy as np
import pytest

import drivesim
from drivesim.carracing import rank, rank_dream, rank_figures
from drivesim.carracing.family import FAMILY, Driver


def test_the_worlds_hidden_state_steps_along_the_behaviour_drive():
    """Where the world is the drivers' own model, its hidden state at each start is the
    driver's, bit for bit."""
    model = drivesim.Model.load()
    sim = drivesim.Simulator(model, batch=4)
    rng = np.random.default_rng(1)
    n, first = 60, 12
    z = rng.standard_normal((n, model.z_dim)).astype(np.float32)
    speed, steer = rng.uniform(10, 50, n).astype(np.float32), rng.uniform(-1, 1, n).astype(np.float32)
    h = np.zeros((n, model.hidden_dim), np.float32)
    for t in range(n - 1):  # as ClonedAgent steps its memory, one decision at a time
        _, h[t + 1] = sim.transition(z[t], h[t], np.array([speed[t], steer[t]], np.float32))
    drive = {"z": z, "h": h, "speed": speed, "steer": steer, "first": np.int64(first)}
    starts = rank_dream.starts_of(drive, sim, model.hidden_dim, 3, 10)
    at = [d - first for d in rank_dream.start_decisions(first + n, 3, 10, first)]
    np.testing.assert_array_equal(starts["h_world"], h[at])
    np.testing.assert_array_equal(starts["h"], h[at])
    np.testing.assert_array_equal(starts["z"], z[at])


def three_starts(seed: int) -> tuple:
    """A simulator for two drivers from three random starts (codes, no memory yet, three speeds, the
    steering before each)."""
    model = drivesim.Model.load()
    rng = np.random.default_rng(seed)
    starts = {"z": rng.standard_normal((3, model.z_dim)).astype(np.float32),
              "h": np.zeros((3, model.hidden_dim), np.float32), "speed": np.float32([30, 40, 50])}
    starts["h_world"], starts["previous"] = starts["h"], np.float32([0.1, -0.2, 0.0])
    return drivesim.Simulator(model, batch=6), starts


def test_the_dream_batch_and_the_value_at_the_horizon():
    """Every driver from every start in one batch: the clone and a driver biased off its line
    differ, one row per start; the value head at the horizon adds its value to each return."""
    sim, starts = three_starts(2)
    family = [FAMILY[0], Driver("b", bias=0.5)]
    plain = rank_dream.dream(sim, sim, family, starts, 6, 0, False)
    valued = rank_dream.dream(sim, sim, family, starts, 6, 0, True)
    assert plain["return"].shape == plain["off_road"].shape == (2, 3)
    assert plain["steer"].shape == plain["off_steps"].shape == (2, 3, 6) and np.all(np.abs(plain["steer"]) <= 1)
    np.testing.assert_allclose(plain["off_steps"].mean(2), plain["off_road"])
    assert np.all(plain["steer"][1] >= plain["steer"][0] - 1e-6)  # the bias pulls right (clipped at 1)
    assert np.isfinite(plain["return"]).all() and ((0 <= plain["off_road"]) & (plain["off_road"] <= 1)).all()
    assert not np.allclose(plain["return"][0], plain["return"][1])
    assert not np.allclose(valued["return"], plain["return"])
    np.testing.assert_array_equal(valued["off_road"], plain["off_road"])


def test_through_frames_the_drivers_read_the_dreams_frames_encoded():
    """``--through-frames``: the drivers act on the codes of the world's frames through their
    encoder, as on a real drive; one decision of it is the policy on those codes, and it is not
    the dream on the codes themselves (which the world still steps on)."""
    sim, starts = three_starts(4)
    family = [FAMILY[0], Driver("b", bias=0.5)]
    seen = rank_dream.dream(sim, sim, family, starts, 1, 0, False, through_frames=True)
    plain = rank_dream.dream(sim, sim, family, starts, 1, 0, False)
    z = rank_dream.tiled(starts["z"], 2)
    expected = np.clip(sim.act(sim.encode(sim.generate(z)), rank_dream.tiled(starts["h"], 2))[:, 1]
                       + np.repeat([0.0, 0.5], 3), -1, 1)
    np.testing.assert_allclose(seen["steer"][:, :, 0].ravel(), expected, atol=1e-6)
    assert not np.allclose(seen["steer"], plain["steer"])
    later = rank_dream.dream(sim, sim, family, starts, 4, 0, False, through_frames=True)
    codes_later = rank_dream.dream(sim, sim, family, starts, 4, 0, False)
    assert np.isfinite(later["return"]).all() and not np.allclose(later["return"], codes_later["return"])


def test_the_dreams_frames_are_handed_out_and_change_nothing():
    """``frames`` receives the world's frame of each decision before the drivers act (the first
    is the start's own code drawn); the dream's figures are the same bits with and without it."""
    sim, starts = three_starts(3)
    family = [FAMILY[0], Driver("b", bias=0.5)]
    shown = []
    kept = rank_dream.dream(sim, sim, family, starts, 4, 0, False, frames=shown)
    plain = rank_dream.dream(sim, sim, family, starts, 4, 0, False)
    assert len(shown) == 4 and shown[0].shape == (6, 80, 160, 3)
    np.testing.assert_array_equal(shown[0], sim.generate(rank_dream.tiled(starts["z"], 2)))
    for key in ("return", "off_steps", "steer"):
        np.testing.assert_array_equal(kept[key], plain[key])


def test_the_world_given_the_dreams_own_inputs_open_loop_is_the_dream():
    """``open_loop`` replays inputs without a driver: given the speeds and steerings a dream
    stepped with, each decision's off-road chance is the dream's, bit for bit."""
    sim, starts = three_starts(3)
    dreamt = rank_dream.dream(sim, sim, [FAMILY[0], Driver("b", bias=0.5)], starts, 6, 0, False)
    given = rank_dream.open_loop(sim, starts, np.stack([dreamt["speed"], dreamt["steer"]], -1))
    np.testing.assert_array_equal(given, dreamt["off_steps"])
    assert dreamt["speed"].shape == (2, 3, 6) and np.all(dreamt["speed"][:, :, 0] == starts["speed"])
    other = rank_dream.open_loop(sim, starts, np.stack([dreamt["speed"], -dreamt["steer"]], -1))
    assert not np.array_equal(other, given)


def test_several_futures_are_the_mean_of_their_dreams_and_their_spread():
    """``--futures N``: the dream from the same starts with sampling seeds 0..N-1, its figures
    their means and each driver's spread over them; one future is the dream a run without the
    option draws, bit for bit, and the world samples with seed 0 after either."""
    from types import SimpleNamespace

    sim, starts = three_starts(4)
    family = [FAMILY[0], Driver("n", noise=0.7)]
    each = []
    for future in range(3):
        sim.set_sampling(1.0, future)
        each.append(rank_dream.dream(sim, sim, family, starts, 6, 5, False))
    args = SimpleNamespace(futures=3, temperature=1.0, horizon=6, value=False, world_steering=(1.0, 0.0),
                           through_frames=False, off_road_read="mean")
    got = rank_dream.dream_futures(sim, sim, family, starts, args, 5)
    assert sim.sampling == (1.0, 0)
    for key in ("return", "rewards", "off_road", "off_steps"):
        np.testing.assert_allclose(got[key], np.mean([d[key] for d in each], 0), rtol=1e-6)
    np.testing.assert_allclose(got["spread"][0], np.std([d["return"] for d in each], 0).mean(1), rtol=1e-6)
    np.testing.assert_allclose(got["spread"][2], np.std([d["off_road"] for d in each], 0).mean(1), rtol=1e-6)
    assert got["spread"].shape == (3, 2) and (got["spread"][0] > 0).all()  # the futures differ
    np.testing.assert_array_equal(got["leaving"], sum(rank_figures.leaving_counts(d["off_steps"]) for d in each))
    args.futures = 1
    one = rank_dream.dream_futures(sim, sim, family, starts, args, 5)
    np.testing.assert_array_equal(one["return"], each[0]["return"])
    assert not one["spread"].any()


def test_the_off_road_share_read_as_the_middle_half_of_the_futures():
    """``--off-road-read midmean``: each start's off-road share is the mean of its futures' middle
    half, each start apart (a split of four futures reads as its two middle ones), and so is each
    decision's chance (the report's table by decision); the returns stay the futures' means."""
    import doctest
    from types import SimpleNamespace

    assert doctest.testmod(rank_dream).failed == 0
    draws = np.array([[0.0, 0.9], [1.0, 0.1], [0.2, 0.5], [0.8, 0.3]])  # 4 futures of 2 starts
    np.testing.assert_allclose(rank_dream.midmean(draws), [0.5, 0.4])
    np.testing.assert_allclose(rank_dream.midmean(draws[:3]), draws[:3].mean(0))  # under 4: the mean
    sim, starts = three_starts(4)
    family = [FAMILY[0], Driver("b", bias=0.5)]
    args = SimpleNamespace(futures=4, temperature=1.0, horizon=8, value=False, world_steering=(1.0, 0.0),
                           through_frames=False, off_road_read="mean")
    mean = rank_dream.dream_futures(sim, sim, family, starts, args, 5)
    args.off_road_read = "midmean"
    middle = rank_dream.dream_futures(sim, sim, family, starts, args, 5)
    each = []
    for future in range(4):
        sim.set_sampling(1.0, future)
        each.append(rank_dream.dream(sim, sim, family, starts, 8, 5, False))
    for key in ("off_road", "off_steps"):  # the share and each decision's chance, read alike
        draws = np.array([d[key] for d in each])
        np.testing.assert_allclose(middle[key], np.sort(draws, 0)[1:3].mean(0), rtol=1e-6)
        np.testing.assert_allclose(mean[key], draws.mean(0), rtol=1e-6)
        assert not np.allclose(middle[key], mean[key])
    for key in ("return", "rewards"):
        np.testing.assert_array_equal(middle[key], mean[key])


def test_the_worlds_steering_shaped_is_its_steering_column_scaled(tmp_path):
    """``--world-steering 2``: the world stepping with twice each steering is the world whose
    transition's steering column is doubled (both exact in floating point), bit for bit, while
    the drivers' memory steps as before, for drivers that never steer past half lock; a lead adds
    the change from the decision before; past full lock the world steps with full lock."""
    from safetensors.numpy import load_file, save_file
    from safetensors import safe_open

    default = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "weights", "default.safetensors")
    tensors = load_file(default)
    with safe_open(default, "np") as f:
        meta = f.metadata()
    tensors["transition.U"] = tensors["transition.U"] * np.float16([1, 2])
    save_file(tensors, tmp_path / "k2.safetensors", metadata=meta)
    sim, starts = three_starts(6)
    doubled = drivesim.Simulator(drivesim.Model.load(tmp_path / "k2.safetensors"), batch=6)
    family = [Driver("half", gain=0.5), Driver("b", gain=0.2, bias=0.3)]   # |steering| <= 0.5
    shaped = rank_dream.dream(sim, sim, family, starts, 6, 0, False, (2.0, 0.0))
    scaled = rank_dream.dream(sim, doubled, family, starts, 6, 0, False)
    np.testing.assert_array_equal(shaped["off_steps"], scaled["off_steps"])
    np.testing.assert_array_equal(shaped["return"], scaled["return"])
    assert not np.array_equal(shaped["return"], rank_dream.dream(sim, sim, family, starts, 6, 0, False)["return"])
    action = np.float32([[30, 0.5], [20, -0.2]])
    np.testing.assert_allclose(rank_dream.world_steering(action, np.float32([0.1, -0.2]), (1.5, 0.5)),
                               [[30, 0.95], [20, -0.3]], rtol=1e-6)
    # Held at full lock: the world is never stepped harder than the real car can steer.
    np.testing.assert_allclose(rank_dream.world_steering(action, np.float32([0.1, -0.9]), (1.5, 1.0)),
                               [[30, 1.0], [20, 0.4]], rtol=1e-6)
    np.testing.assert_array_equal(rank_dream.world_steering(np.float32([[50, -0.9]]), -0.5, (1.4, 0.0)), [[50, -1.0]])
    assert rank_dream.world_steering(action, 0.0, (1.0, 0.0)) is action
    assert rank.shaping("2") == (2.0, 0.0) and rank.shaping("1.5,0.5") == (1.5, 0.5)
    with pytest.raises(ValueError):
        rank.shaping("1,nan")


def test_start_decisions_leave_the_horizon_and_refuse_a_short_drive():
    starts = rank_dream.start_decisions(250, 7, 40, 12)
    assert len(starts) == 7 and starts[0] == 20 and starts[-1] == 250 - 40
    assert rank_dream.start_decisions(180, 2, 40, 12) == [20, 140]  # a lap finished early
    with pytest.raises(ValueError, match="no start"):
        rank_dream.start_decisions(25, 2, 40, 12)

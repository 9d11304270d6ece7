"""The driver learnt in the dream (drivesim.carracing.dreamt, dream_train): the controller, its
batched rollouts, the agent against the clone, training resumed to the same bytes."""

import json
import os
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

import drivesim
from drivesim import episodes
from drivesim.carracing import make_agent
from drivesim.carracing.dream_curve import main as dream_curve
from drivesim.carracing.dream_train import main, train
from drivesim.carracing.dreamt import Controller, rollout


@pytest.fixture(scope="module")
def starts_file(tmp_path_factory):
    """Two episodes of 30 random frames with speeds and steering: real states enough for the
    controller's mechanics (their codes are the model's for these frames)."""
    rng = np.random.default_rng(4)
    frames = rng.integers(0, 256, (60, 80, 160, 3), dtype=np.uint8)
    actions = np.stack([rng.uniform(15, 45, 60), rng.uniform(-0.5, 0.5, 60)], 1).astype(np.float32)
    path = tmp_path_factory.mktemp("starts") / "starts.safetensors"
    episodes.write(path, episodes.Episodes(frames, actions, np.array([0, 30])), {"frame_hz": "12.5"})
    return path


def controller(model, base="fresh", features=4, seed=0):
    rng = np.random.default_rng(seed)
    z, h = rng.standard_normal((50, model.z_dim)), rng.standard_normal((50, model.hidden_dim))
    return Controller.fit(z, h, features, base, (10.0, 58.8) if base == "fresh" else (10.0, 1.0))


def test_a_zero_controller_on_the_clone_drives_as_the_clone(model):
    frames = np.random.default_rng(1).integers(0, 256, (16, 80, 160, 3), dtype=np.uint8)
    clone = make_agent("cloned", pace=None)  # the controller gives the speed: no racing pace
    dreamt = make_agent("dreamt", controller=controller(model, "cloned"))
    for i, frame in enumerate(frames):
        assert np.array_equal(clone.act(frame, 20.0 + i), dreamt.act(frame, 20.0 + i)), i
    assert dreamt.decisions == 16 > dreamt.warmup


def test_a_fresh_zero_controller_steers_straight_at_the_middle_speed(model):
    agent = make_agent("dreamt", controller=controller(model))
    z = np.zeros(model.z_dim, np.float32)
    assert agent.decide(z) == (pytest.approx((10.0 + 58.8) / 2), 0.0)


def test_without_a_controller_the_built_in_driver_drives_at_its_own_speed():
    """Without options `dreamt` drives the built-in driver learnt in the default's dream (its
    policy head, `Model.dreamt()`): as the clone's agent would drive that head with every
    hand-made aid off, the traction control aside. A file whose policy is the clone (it has the
    pace head) or that has no policy is refused."""
    from conftest import REPO, fixture

    from drivesim.carracing.cloned import ClonedAgent

    frames = np.random.default_rng(3).integers(0, 256, (16, 80, 160, 3), dtype=np.uint8)
    bare = ClonedAgent(drivesim.Model.dreamt(), pace=None, grip=None, traction=False, bearings=False)
    dreamt, held = make_agent("dreamt", traction=False), make_agent("dreamt")
    assert held.traction is not None and dreamt.traction is None
    for i, frame in enumerate(frames):
        assert np.array_equal(bare.act(frame, 40.0 - i), dreamt.act(frame, 40.0 - i)), i
    with pytest.raises(ValueError, match="controller=FILE"):
        make_agent("dreamt", weights=fixture("small_f32.safetensors"))
    with pytest.raises(ValueError, match="pace head"):
        make_agent("dreamt", weights=os.path.join(REPO, "weights", "default.safetensors"))


def test_traction_eases_the_gas_in_turns_and_cuts_it_while_the_wheels_spin(model):
    """traction=True: the learnt driver's speed control is the racing one (less gas with the
    wheels turned) with the traction control: gas that did not make the slow car faster is cut.
    The driver's own decisions, the steering among them, do not change."""
    from drivesim.carracing.control import speed_control

    z = np.random.default_rng(0).standard_normal(model.z_dim).astype(np.float32)  # target 30.8, steer 0.26
    frame = np.zeros((80, 160, 3), np.uint8)  # drive() reads the code; the frame is for aids it has not
    bare, held = make_agent("dreamt", traction=False), make_agent("dreamt", traction=True)
    target, steer = bare.choose(z, bare.h)
    first, eased = bare.drive(frame, z, 10.0), held.drive(frame, z, 10.0)
    assert eased[0] == first[0] == steer and first[1] == pytest.approx(speed_control(10.0, target)[0])
    assert eased[1] == pytest.approx(speed_control(10.0, target, steer)[0]) and 0.2 <= eased[1] < first[1]
    bare_again, cut = bare.drive(frame, z, 10.0), held.drive(frame, z, 10.0)  # the gas gained nothing
    assert bare_again[1] >= 0.2 and cut[1] == 0.0 and cut[0] == bare_again[0]
    with pytest.raises(TypeError, match="traction"):
        make_agent("dreamt", traction="yes")
    with pytest.raises(ValueError, match="traction"):
        make_agent("dreamt", traction=2)


def test_anticipate_slows_for_the_steering_the_driver_dreams_ahead_and_only_slows(model):
    """anticipate=D: a driver at full lock in its own dream is held to the grip envelope of full
    lock (``brake_ahead`` of its plan), braking from 50 where it asked for 58.8; a slow car's
    decisions are bit for bit those without the option; the steering is never touched."""
    from drivesim.carracing.control import brake_ahead, speed_control
    from drivesim.carracing.dreamt import ANTICIPATE_HORIZON

    full_lock = controller(model)
    full_lock.weights[:] = 0.0
    full_lock.weights[:, -1] = (20.0, 3.0)  # target ~58.8, steering tanh(3)
    frame, z = np.zeros((80, 160, 3), np.uint8), np.zeros(model.z_dim, np.float32)
    bare = make_agent("dreamt", controller=full_lock)
    ahead = make_agent("dreamt", controller=full_lock, anticipate=10)
    target, steer = bare.choose(z, bare.h)
    limit = brake_ahead(np.full(ANTICIPATE_HORIZON, steer), 10.0)
    assert 45.0 < limit < 46.0 < target
    fast_bare, fast_ahead = bare.drive(frame, z, 50.0), ahead.drive(frame, z, 50.0)
    assert fast_ahead[0] == fast_bare[0] == np.float32(steer)
    assert fast_bare[1:] == pytest.approx(speed_control(50.0, target)) and fast_bare[2] == 0.0
    assert fast_ahead[1:] == pytest.approx(speed_control(50.0, limit)) and fast_ahead[1] == 0.0 < fast_ahead[2]
    frames = np.random.default_rng(5).integers(0, 256, (16, 80, 160, 3), dtype=np.uint8)
    pairs = [(make_agent("dreamt", traction=t), make_agent("dreamt", traction=t, anticipate=10)) for t in (0, 1)]
    for i, frame in enumerate(frames):
        for without, with_it in pairs:
            assert np.array_equal(without.act(frame, 12.0 + i), with_it.act(frame, 12.0 + i)), i
    assert with_it.decisions == 16 > with_it.warmup
    with pytest.raises(ValueError, match="anticipate"):
        make_agent("dreamt", anticipate=-1)
    with pytest.raises(TypeError, match="anticipate"):
        make_agent("dreamt", anticipate="soon")


def test_controller_files_round_trip_and_bad_ones_are_named(model, tmp_path):
    c = controller(model, "cloned")
    c = c.with_weights(np.random.default_rng(0).standard_normal(c.weights.shape), 7)
    c.save(tmp_path / "c.npz")
    back = Controller.load(tmp_path / "c.npz")
    assert back.base == "cloned" and back.generation == 7 and np.array_equal(back.weights, c.weights)
    (tmp_path / "junk.npz").write_bytes(b"not a controller")
    with pytest.raises(ValueError, match="junk.npz: not a controller file"):
        Controller.load(tmp_path / "junk.npz")
    with pytest.raises(ValueError, match="disagree"):
        Controller(c.centre, c.scale, c.projection, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="limits 5.0, 3.0"):
        Controller(c.centre, c.scale, c.projection, c.weights, "cloned", (5.0, 3.0))
    small = Controller(np.zeros(3), np.ones(3), np.eye(3)[:2], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="reads 3 numbers"):
        make_agent("dreamt", controller=small)


def test_a_population_is_rolled_in_one_batch_from_the_same_starts(model):
    sim = drivesim.Simulator(model, batch=3 * 4)
    rng = np.random.default_rng(2)
    starts = {"z": rng.standard_normal((4, model.z_dim)).astype(np.float32),
              "h": np.zeros((4, model.hidden_dim), np.float32), "speed": np.full(4, 30.0, np.float32)}
    c = controller(model)
    w = rng.standard_normal(c.weights.shape)
    population = c.with_weights(np.stack([w, w, -w]), 0)
    returns, off_road = rollout(sim, population, starts, 6, off_road_steps=2, use_value=True, off_road_cost=1.0)
    assert returns.shape == off_road.shape == (3, 4)
    assert np.array_equal(returns[0], returns[1]) and not np.array_equal(returns[0], returns[2])
    assert np.all((0 <= off_road) & (off_road <= 1))
    # One controller alone, step by step, is the population's first row: the batch changes no bit.
    alone = drivesim.Simulator(model, batch=4)
    assert np.array_equal(rollout(alone, c.with_weights(w[None], 0), starts, 6, 2, True, 1.0)[0][0], returns[0])
    # Sampled: the same draws for the same seed.
    sim.set_sampling(1.0, 9)
    sampled = rollout(sim, population, starts, 6)[0]
    sim.set_sampling(1.0, 9)
    assert np.array_equal(sampled, rollout(sim, population, starts, 6)[0])
    sim.set_sampling(0.0, 9)
    assert not np.array_equal(sampled, rollout(sim, population, starts, 6)[0])


def arguments(starts, out, generations):
    return SimpleNamespace(world=None, starts=starts, dir=out, generations=generations, population=4,
                           starts_per_generation=3, horizon=4, temperature=1.0, off_road_steps=2, off_road_cost=1.0,
                           value=True, base="fresh", limits=None, features=3, sigma=0.5, seed=1, save_every=2,
                           threads=1)


def test_a_run_stopped_and_started_again_ends_with_the_same_bytes(starts_file, tmp_path):
    quiet = lambda *_: None  # noqa: E731
    whole = train(arguments(starts_file, tmp_path / "whole", 4), log=quiet)
    train(arguments(starts_file, tmp_path / "parts", 1), log=quiet)
    train(arguments(starts_file, tmp_path / "parts", 4), log=quiet)
    for name in ("state.npz", "controller.npz", "controller_0002.npz", "controller_0004.npz"):
        assert (tmp_path / "whole" / name).read_bytes() == (tmp_path / "parts" / name).read_bytes(), name
    log = [json.loads(line) for line in (tmp_path / "parts" / "log.jsonl").read_text().splitlines()]
    assert [line["generation"] for line in log] == [1, 2, 3, 4] and whole.generation == 4
    with pytest.raises(ValueError, match="other settings"):
        train(SimpleNamespace(**{**vars(arguments(starts_file, tmp_path / "whole", 4)), "horizon": 5}), log=quiet)


def test_the_curve_sets_the_dream_beside_the_real_track(starts_file, tmp_path, capsys):
    pytest.importorskip("Box2D")
    train(arguments(starts_file, tmp_path / "run", 4), log=lambda *_: None)
    assert dream_curve(["--dir", str(tmp_path / "run"), "--tracks", "5", "--every", "2", "--frames", "80",
                        "--workers", "1", "--threads", "1"]) == 0
    curve = json.loads((tmp_path / "run" / "curve.json").read_text())
    assert [row["generation"] for row in curve["rows"]] == [0, 2, 4] and curve["real_episodes"] == 3
    assert all(len(row["real"]) == 1 and np.isfinite(row["dream_return"]) for row in curve["rows"])
    assert "generation    4: dream" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        dream_curve(["--dir", str(tmp_path), "--tracks", "5"])  # not a run


def test_a_killed_run_resumes_to_the_same_bytes(starts_file, tmp_path):
    def command(out):
        return [sys.executable, "-m", "drivesim", "dream-train", "--starts", str(starts_file), "--dir", str(out),
                "--generations", "30", "--population", "8", "--starts-per-generation", "8", "--horizon", "8",
                "--features", "4", "--threads", "1", "--save-every", "10"]

    subprocess.run(command(tmp_path / "whole"), check=True, capture_output=True, timeout=600)
    run = subprocess.Popen(command(tmp_path / "killed"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not (tmp_path / "killed" / "controller_0010.npz").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(run.pid, signal.SIGKILL)
    run.wait()
    assert not (tmp_path / "killed" / "controller.npz").exists(), "the run ended before the kill"
    subprocess.run(command(tmp_path / "killed"), check=True, capture_output=True, timeout=600)
    for name in ("state.npz", "controller.npz", "controller_0030.npz"):
        assert (tmp_path / "whole" / name).read_bytes() == (tmp_path / "killed" / name).read_bytes(), name


def test_the_command_s_bad_input_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--starts", str(tmp_path / "missing.safetensors"), "--dir", str(tmp_path / "d")])
    assert stop.value.code == 2 and "missing.safetensors: no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--starts", str(tmp_path), "--dir", str(tmp_path / "d"), "--population", "2"])

"""The bridge to the real CarRacing: the models' view, and the agents."""

import json
import os

import numpy as np
import pytest

import drivesim
from drivesim import carracing


@pytest.mark.parametrize("name", ["mpc", "mpc-road"])
def test_planners_are_deterministic(name, clip):
    frames, actions = clip
    runs = []
    for _ in range(2):
        agent = carracing.make_agent(name)
        agent.warmup = 0
        runs.append([agent.act(f, float(a[0])) for f, a in zip(frames, actions)])
    np.testing.assert_array_equal(np.array(runs[0]), np.array(runs[1]))
    action = runs[0][-1]
    assert action.dtype == np.float32 and action.shape == (3,)
    assert -1 <= action[0] <= 1 and action[1] >= 0 and action[2] >= 0
    assert agent.imagine().shape == (agent.horizon, 80, 160, 3)


def test_unknown_agent():
    with pytest.raises(ValueError, match="mpc"):
        carracing.make_agent("nope")


def test_speed_control():
    assert carracing.speed_control(10.0, 40.0)[0] > 0
    assert carracing.speed_control(60.0, 20.0)[1] > 0
    # With the steering: TURN_GAS of the gas off at full lock, none straight ahead, the brake kept.
    assert carracing.speed_control(10.0, 40.0, 0.0) == carracing.speed_control(10.0, 40.0)
    assert carracing.speed_control(10.0, 40.0, -1.0)[0] == pytest.approx(0.5 * carracing.speed_control(10.0, 40.0)[0])
    assert carracing.speed_control(60.0, 20.0, 0.7) == carracing.speed_control(60.0, 20.0)
    with pytest.raises(ValueError, match="steer"):
        carracing.speed_control(10.0, 40.0, 1.5)


def test_observe_is_the_recorded_view():
    pytest.importorskip("Box2D")
    import gymnasium

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    env = gymnasium.make("CarRacing-v3")
    env.reset(seed=1)
    for _ in range(60):
        env.step(np.float32([0.0, 0.3, 0.0]))
    frame = carracing.observe(env)
    assert frame.shape == (80, 160, 3) and frame.dtype == np.uint8
    # The car sits at the bottom centre of the view, on grey road.
    road = drivesim.road.measure(frame[None])[0]
    assert road[3] > 0.3 and abs(road[0]) < 20
    assert carracing.speed(env) > 5
    env.close()


def test_evaluation_command(tmp_path, capsys):
    pytest.importorskip("Box2D")
    from drivesim.carracing.__main__ import main

    main(["--agent", "mpc", "--seeds", "7", "--frames", "80", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert "mpc:" in out and (tmp_path / "track_7.json").exists() and (tmp_path / "track_7.gif").exists()
    # What planning adds: the departures from the policy and the policy alone on the same track.
    figures = json.loads((tmp_path / "track_7.json").read_text())
    assert 0 <= figures["departed"] <= 1 and np.isfinite(figures["policy_alone"])
    assert figures["speed_change"] >= 0 and figures["steer_change"] >= 0
    assert "the policy alone:" in out and "mpc - policy" in out
    # Resumable: a second run reads the track's figures instead of driving it again.
    main(["--agent", "mpc", "--seeds", "7", "--frames", "80", "--out", str(tmp_path)])
    assert capsys.readouterr().out.splitlines()[-2] == out.splitlines()[-2]


def test_evaluation_without_animations(tmp_path, capsys):
    pytest.importorskip("Box2D")
    from drivesim.carracing.__main__ import main

    # The figures, resumable, without the animation: the same drive, to the same reward.
    main(["--agent", "cloned", "--seeds", "7", "--frames", "60", "--out", str(tmp_path / "a"), "--no-gif"])
    main(["--agent", "cloned", "--seeds", "7", "--frames", "60", "--out", str(tmp_path / "b")])
    capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["track_7.json"]
    a, b = (json.loads((tmp_path / d / "track_7.json").read_text()) for d in "ab")
    assert a["reward"] == b["reward"] and a["frames"] == b["frames"] == 60
    with pytest.raises(SystemExit):  # nowhere to write the figures
        main(["--agent", "cloned", "--seeds", "7", "--no-gif"])
    assert "--no-gif goes with --out" in capsys.readouterr().err


def test_baselines_act_in_range(clip):
    frames, actions = clip
    for name in ("reactive", "random"):
        a, b = carracing.make_agent(name), carracing.make_agent(name)
        for f, act in zip(frames, actions):
            x, y = a.act(f, float(act[0])), b.act(f, float(act[0]))
            np.testing.assert_array_equal(x, y)  # deterministic
            assert x.dtype == np.float32 and -1 <= x[0] <= 1 and 0 <= x[1] <= 1 and 0 <= x[2] <= 1


def test_cloned_agent_is_the_policy_stepped_along_the_drive(model, clip):
    frames, actions = clip
    agent = carracing.make_agent("cloned", pace=None)
    agent.warmup = 0
    sim = drivesim.Simulator(model)
    h = np.zeros(model.hidden_dim, np.float32)
    for frame, recorded in zip(frames, actions):
        speed = float(recorded[0])
        action = agent.act(frame, speed)
        # The same by hand: the policy on the code and the hidden state, then a transition step.
        z = sim.encode(frame)
        target, steer = sim.act(z, h)
        _, h = sim.transition(z, h, np.array([speed, steer], np.float32))
        np.testing.assert_array_equal(action[0], np.float32(steer))
        np.testing.assert_array_equal(action[1:], np.float32(carracing.speed_control(speed, float(target))))
    assert action.dtype == np.float32 and -1 <= action[0] <= 1
    assert agent.imagine(3).shape == (3, 80, 160, 3)
    agent.reset()
    assert agent.imagine() is None and not agent.h.any()


def test_cloned_agent_at_racing_pace(model, clip):
    """The default drives at the pace head's speed where the policy's is at the top of its range
    (at most ``pace``), at the lower of the two below it, under the grip envelope where that is
    faster than the policy, with the steering's gas rule."""
    from drivesim.carracing.cloned import AT_THE_TOP, GRIP, PACE
    from drivesim.carracing.control import grip_speed

    frames, actions = clip
    assert model.pace_width == 192
    agent = carracing.make_agent("cloned")
    assert agent.pace == PACE and agent.grip == GRIP == 1.0
    agent.warmup = 0
    sim = drivesim.Simulator(model)
    h = np.zeros(model.hidden_dim, np.float32)
    top = model.actions[0]["max"]
    for frame, recorded in zip(frames, actions):
        speed = float(recorded[0])
        action = agent.act(frame, speed)
        z = sim.encode(frame)
        target, steer = sim.act(z, h)
        pace = float(sim.pace(z, h)[0])
        paced = min(pace if target >= top - AT_THE_TOP else min(pace, float(target)), PACE)
        if paced > target:
            paced = min(paced, grip_speed(float(steer)))
        _, h = sim.transition(z, h, np.array([speed, steer], np.float32))
        np.testing.assert_array_equal(action[0], np.float32(steer))
        np.testing.assert_array_equal(action[1:], np.float32(carracing.speed_control(speed, paced, float(steer))))
    # Each branch of the rule on the last state: at the top (the boundary included) the pace
    # head's speed, below it the lower of the two, never above the cap.
    free = carracing.make_agent("cloned", pace=1e4, grip=None)
    free.h, pace = h, float(sim.pace(z, h)[0])
    assert free.paced(z, top) == free.paced(z, top - AT_THE_TOP) == pace > top
    assert free.paced(z, top - 2 * AT_THE_TOP) == top - 2 * AT_THE_TOP and free.paced(z, 10.0) == 10.0
    agent.h = h
    assert agent.paced(z, top) == min(pace, PACE)
    # The grip envelope: steered hard, no faster than the expert ever drove so steered (the
    # policy's own speed kept where that is lower); steered straight, the pace head's.
    assert pace > grip_speed(0.5) and agent.paced(z, top, steer=0.5) == grip_speed(0.5) == agent.paced(z, top, -0.5)
    assert agent.paced(z, 40.0, steer=0.5) == min(pace, 40.0)
    assert carracing.make_agent("cloned", grip=0.5, pace=1e4).paced(z, 10.0, steer=1.0) == 10.0
    # A slower cap changes the drive; pace=None is the policy alone; a model without the head
    # drives at its policy's speed whatever the option.
    slow = carracing.make_agent("cloned", pace=30.0)
    slow.warmup = 0
    assert any(slow.act(f, float(a[0]))[1] != agent.act(f, float(a[0]))[1] for f, a in zip(frames, actions))
    for bad, error in ((0.0, ValueError), (-5.0, ValueError), (float("nan"), ValueError), ("fast", TypeError)):
        with pytest.raises(error, match="pace"):
            carracing.make_agent("cloned", pace=bad)
    for name in ("cloned", "mpc"):
        for bad, error in ((0.4, ValueError), (2.5, ValueError), (float("inf"), ValueError), ("firm", TypeError)):
            with pytest.raises(error, match="grip"):
                carracing.make_agent(name, grip=bad)


def test_grip_envelope():
    """The expert's grip envelope: slower the harder the wheels are turned, the same either way,
    the bins' speeds at their centres and the ends held; the steering checked."""
    from drivesim.carracing.control import GRIP_SPEED, GRIP_STEER, grip_speed

    assert list(GRIP_SPEED) == sorted(GRIP_SPEED, reverse=True) and list(GRIP_STEER) == sorted(GRIP_STEER)
    assert [grip_speed(s) for s in GRIP_STEER] == list(GRIP_SPEED)
    assert grip_speed(0.0) == GRIP_SPEED[0] and grip_speed(-1.0) == grip_speed(1.0) == GRIP_SPEED[-1]
    assert grip_speed(0.3) == grip_speed(-0.3) and GRIP_SPEED[4] < grip_speed(0.3) < GRIP_SPEED[3]
    for bad, error in ((1.5, ValueError), (float("nan"), ValueError), (None, TypeError)):
        with pytest.raises(error, match="steer"):
            grip_speed(bad)


def test_wheelspin_traction_control():
    """Gas that did not make a slow car faster is cut, then held low for ``HOLD`` decisions;
    gas that did, a fast car, or gas too light to spin the wheels are left alone."""
    from drivesim.carracing.control import Wheelspin

    spin = Wheelspin()
    assert [spin.gas(s, 0.6) for s in (10.0, 14.0, 18.0)] == [0.6, 0.6, 0.6] and spin.spins == 0
    assert spin.gas(18.2, 0.6) == 0.0 and spin.spins == 1  # no faster under full gas: spinning
    held = [spin.gas(18.0 + k, 0.6) for k in range(Wheelspin.HOLD)]
    assert held == [Wheelspin.HOLD_GAS] * Wheelspin.HOLD and spin.gas(50.0, 0.6) == 0.6
    assert spin.gas(45.0, 0.6) == 0.6 and spin.gas(45.0, 0.6) == 0.6  # a fast car: no wheelspin
    spin.reset()
    assert spin.gas(10.0, 0.1) == 0.1 and spin.gas(10.0, 0.1) == 0.1 and spin.spins == 0
    # Held gas that still gains nothing is a wheelspin again: cut, and the hold starts over.
    spin.reset()
    assert [spin.gas(20.0, 0.6), spin.gas(20.0, 0.6), spin.gas(20.1, 0.6), spin.gas(20.2, 0.6)] == [0.6, 0.0, 0.2, 0.0]
    for name in ("cloned", "mpc"):
        assert carracing.make_agent(name).traction is not None
        assert carracing.make_agent(name, traction=False).traction is None
        assert carracing.make_agent(name, pace=None).traction is None  # the policy's own speed: as before
        for bad, error in ((2, ValueError), (0.5, ValueError), ("on", TypeError), (None, TypeError)):
            with pytest.raises(error, match="traction"):
                carracing.make_agent(name, traction=bad)


def test_grip_envelope_fit(tmp_path, capsys):
    """``python -m drivesim grip``: a high percentile of the speed per bin of |steer|, falling as
    the steering grows, sparse bins left out; what it prints is what control.py holds."""
    from drivesim.carracing import grip

    rng = np.random.default_rng(0)
    steer = rng.uniform(-0.2, 0.2, 4000)  # two bins' worth and more: 0-0.05, 0.05-0.1, 0.1-0.2
    speed = 80.0 - 100.0 * np.abs(steer) * rng.uniform(0.0, 1.0, 4000) ** 0.01
    centres, speeds, counts = grip.envelope(np.stack([speed, steer], 1), quantile=100.0)
    assert centres == (0.025, 0.075, 0.15) and sum(counts) == 4000
    assert speeds[0] == pytest.approx(80.0, abs=0.5) and speeds[2] == pytest.approx(70.0, abs=0.5)
    # A faster bin past a slower one is held to the slower's speed; too few decisions: no bin.
    rows = np.array([[50.0, 0.01]] * 30 + [[60.0, 0.07]] * 30 + [[99.0, 0.9]] * 5)
    assert grip.envelope(rows) == ((0.025, 0.075), (50.0, 50.0), (30, 30))
    for bad in (np.zeros((5, 3)), np.array([[np.nan, 0.0]] * 30), rows[-5:]):
        with pytest.raises(ValueError):
            grip.envelope(bad)
    with pytest.raises(ValueError, match="quantile"):
        grip.envelope(rows, quantile=0.0)
    with pytest.raises(SystemExit, match="grip: .*no such file"):
        grip.main(["--episodes", str(tmp_path / "missing.safetensors.gz")])


def test_cloned_agent_needs_a_policy():
    from conftest import fixture

    with pytest.raises(ValueError, match="no policy"):
        carracing.make_agent("cloned", weights=fixture("small_f32.safetensors"))


def test_speed_model_is_the_controllers_pace():
    from drivesim.carracing.control import ACCELERATION, speed_after, speeds_reached

    assert speed_after(40.0, 45.0) == pytest.approx(41.0)  # a gain of the gap...
    assert speed_after(40.0, 90.0) == pytest.approx(40.0 + ACCELERATION)  # ...up to the car's
    assert speed_after(40.0, 37.0) == 40.0  # the brake's dead band
    assert speed_after(40.0, 20.0) == 20.0  # braking hard gets there within the decision
    plans = np.float32([[90, 90, 90, 10], [40, 40, 40, 40]])
    reached = speeds_reached(40.0, plans)
    assert reached.shape == plans.shape and (reached[:, 0] == 40.0).all()
    np.testing.assert_allclose(reached[0], [40, 42, 44, 46])
    np.testing.assert_allclose(reached[1], 40.0)
    for bad in ((float("nan"), 40.0), (40.0, [1.0, float("inf")])):
        with pytest.raises(ValueError, match="finite"):
            speed_after(*bad)
    with pytest.raises(ValueError, match="targets"):
        speeds_reached(40.0, 50.0)


def test_planner_dreams_at_the_speed_the_car_reaches(model, clip):
    """The dream's speed was the policy's target: for a policy that asks for far more than
    the car reaches in a decision, a dream of a car that is not there."""
    from drivesim.carracing.control import speed_after

    frames, _ = clip
    agent = carracing.MPCAgent(model)
    z, h = agent.sim.encode(frames[0]), np.zeros(model.hidden_dim, np.float32)
    speeds, transition = [], agent.sim.transition
    agent.sim = type("Recorder", (), {"act": agent.sim.act, "transition": lambda self, z, h, a: (
        speeds.append(float(a[0])), transition(z, h, a))[1]})()
    targets, _ = agent.prior(z, h, 5.0)  # far below the policy's targets
    assert speeds[0] == 5.0 and targets[0] > 5.0 + 10
    for t in range(1, len(speeds)):
        assert speeds[t] == pytest.approx(float(speed_after(speeds[t - 1], targets[t - 1])))
    assert speeds[1] < targets[0]


def test_guarded_planner_keeps_the_policy_where_the_dream_keeps_it_on_the_road(clip):
    """``guard``: below the policy's own plan's off-road chance the planner weighs the
    candidates as without it; above it, it acts exactly as the cloned driver."""
    from drivesim.carracing.__main__ import option

    frames, actions = clip

    def drive(agent):
        agent.warmup = 0
        return np.array([agent.act(f, float(a[0])) for f, a in zip(frames, actions)])

    assert carracing.make_agent("mpc").guard == 0.1 and option("guard=none") == ("guard", None)
    plain = drive(carracing.make_agent("mpc", guard=None))
    never = carracing.make_agent("mpc", guard=0.0)
    np.testing.assert_array_equal(drive(never), plain)
    assert never.guarded == 0
    always = carracing.make_agent("mpc", guard=1.0)
    kept = drive(always)
    assert always.guarded == always.planned == len(frames) and always.departures == 0
    np.testing.assert_array_equal(kept, drive(carracing.make_agent("cloned")))  # racing pace included
    unpaced = carracing.make_agent("mpc", guard=1.0, pace=None)
    np.testing.assert_array_equal(drive(unpaced), drive(carracing.make_agent("cloned", pace=None)))
    assert not np.array_equal(kept, plain)  # the candidates do move the plain planner
    with pytest.raises(ValueError, match="guard"):
        carracing.make_agent("mpc", guard=1.5)


def test_brake_ahead_slows_before_the_bend_the_plan_steers_into():
    """``brake_ahead``: the envelope of the sharpest steering ahead, plus what the car can shed
    on the way there; the plan checked."""
    from drivesim.carracing.control import GRIP_SPEED, brake_ahead, grip_speed

    assert brake_ahead([0.0] * 8, 10.0) == GRIP_SPEED[0]  # a straight: the envelope's top
    assert brake_ahead([0.0, 0.0, 0.5], 10.0) == pytest.approx(grip_speed(0.5) + 20.0)
    assert brake_ahead([0.0, 0.0, -0.5], 0.0) == pytest.approx(grip_speed(0.5))  # either way
    assert brake_ahead([0.9, 0.0], 10.0, grip=0.5) == pytest.approx(0.5 * grip_speed(0.9))
    for bad, error in (([], ValueError), ([1.5], ValueError), ([[0.1]], ValueError), ([float("nan")], ValueError)):
        with pytest.raises(error, match="steers"):
            brake_ahead(bad, 10.0)
    with pytest.raises(ValueError, match="decel"):
        brake_ahead([0.1], -1.0)


def test_anticipating_planner_drives_no_faster_than_its_plan_allows(clip):
    """``anticipate``: the gas is never more, the brake never less, than the same planner's
    without it, and where the plan steers ahead it slows; off by default; the option checked."""
    frames, actions = clip
    assert carracing.make_agent("mpc").anticipate is None
    plain, slow = carracing.make_agent("mpc", guard=1.0), carracing.make_agent("mpc", guard=1.0, anticipate=0.0)
    plain.warmup = slow.warmup = 0
    # At 90 units/s the envelope of the plan's larger steerings ahead is below the speed.
    a = np.array([plain.act(f, 90.0) for f in frames])
    b = np.array([slow.act(f, 90.0) for f in frames])
    np.testing.assert_array_equal(a[:, 0], b[:, 0])  # the steering is the policy's either way
    assert (b[:, 1] <= a[:, 1]).all() and (b[:, 2] >= a[:, 2]).all() and (b[:, 2] > a[:, 2]).any()
    for bad, error in ((-1.0, ValueError), (101.0, ValueError), ("fast", TypeError)):
        with pytest.raises(error, match="anticipate"):
            carracing.make_agent("mpc", anticipate=bad)

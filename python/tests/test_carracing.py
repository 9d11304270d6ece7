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
    (at most ``pace``), at the lower of the two below it, with the steering's gas rule."""
    from drivesim.carracing.cloned import AT_THE_TOP, PACE

    frames, actions = clip
    assert model.pace_width == 192
    agent = carracing.make_agent("cloned")
    assert agent.pace == PACE
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
        _, h = sim.transition(z, h, np.array([speed, steer], np.float32))
        np.testing.assert_array_equal(action[0], np.float32(steer))
        np.testing.assert_array_equal(action[1:], np.float32(carracing.speed_control(speed, paced, float(steer))))
    # Each branch of the rule on the last state: at the top (the boundary included) the pace
    # head's speed, below it the lower of the two, never above the cap.
    free = carracing.make_agent("cloned", pace=1e4)
    free.h, pace = h, float(sim.pace(z, h)[0])
    assert free.paced(z, top) == free.paced(z, top - AT_THE_TOP) == pace > top
    assert free.paced(z, top - 2 * AT_THE_TOP) == top - 2 * AT_THE_TOP and free.paced(z, 10.0) == 10.0
    agent.h = h
    assert agent.paced(z, top) == min(pace, PACE)
    # A slower cap changes the drive; pace=None is the policy alone; a model without the head
    # drives at its policy's speed whatever the option.
    slow = carracing.make_agent("cloned", pace=30.0)
    slow.warmup = 0
    assert any(slow.act(f, float(a[0]))[1] != agent.act(f, float(a[0]))[1] for f, a in zip(frames, actions))
    for bad, error in ((0.0, ValueError), (-5.0, ValueError), (float("nan"), ValueError), ("fast", TypeError)):
        with pytest.raises(error, match="pace"):
            carracing.make_agent("cloned", pace=bad)


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

    assert carracing.make_agent("mpc").guard == 0.05 and option("guard=none") == ("guard", None)
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

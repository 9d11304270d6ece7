"""The reward and value heads from Python: `Simulator.reward`, `value` and
`rollout_candidates_scored`, as a step-by-step rollout gives them; typed errors."""

import numpy as np
import pytest
from conftest import fixture

import drivesim
from drivesim import carracing


def test_the_default_has_its_heads(model):
    assert model.reward_width == 64 and model.value_width == 64 and model.pace_width == 192
    assert 0 < model.discount < 1
    sim = drivesim.Simulator(model, batch=3)
    z = np.random.default_rng(1).normal(size=(3, model.z_dim)).astype(np.float32)
    h = np.random.default_rng(2).uniform(-1, 1, size=(3, model.hidden_dim)).astype(np.float32)
    pace = sim.pace(z, h)
    assert pace.shape == (3, 1) and pace.dtype == np.float32 and (pace >= 0).all()
    np.testing.assert_array_equal(sim.pace(z[1], h[1]), pace[1])


def test_scored_candidates_are_their_own_rollouts_scored(model, clip):
    frames, actions = clip
    sim = drivesim.Simulator(model, batch=5, threads=2)
    z, h = sim.encode(frames[0]), np.zeros(model.hidden_dim, np.float32)
    _, h = sim.transition(z, h, actions[0])
    z = sim.encode(frames[1])
    steps, n = 4, 5
    plan = np.zeros((steps, n, 2), np.float32)
    plan[..., 0] = 40.0
    plan[..., 1] = np.linspace(-0.6, 0.6, n)[None, :]
    codes, rewards, values = sim.rollout_candidates_scored(h, plan, z=z)
    assert (codes.shape, rewards.shape, values.shape) == ((steps, n, model.z_dim), (steps, n, 2), (steps, n))
    np.testing.assert_array_equal(codes, sim.rollout_candidates(h, plan, z=z))
    one = drivesim.Simulator(model)
    for k in range(n):
        zk, hk = z, h
        for t in range(steps):
            if t == 0:
                zk, hk = one.transition(zk, hk, plan[t, k])
            else:
                zk, hk = one.transition_fed_back(hk, plan[t, k])
            np.testing.assert_array_equal(one.reward(zk, hk), rewards[t, k])
            np.testing.assert_array_equal(one.value(zk, hk), values[t, k : k + 1])
    assert ((rewards[..., 1] >= 0) & (rewards[..., 1] <= 1)).all()
    batch = sim.reward(codes[0], np.repeat(h[None], n, axis=0))
    assert batch.shape == (n, 2) and sim.value(codes[0], np.repeat(h[None], n, axis=0)).shape == (n, 1)


def test_heads_raise_typed_errors(model):
    plain = drivesim.Model.load(fixture("small_f32.safetensors"))
    assert (plain.reward_width, plain.value_width, plain.discount) == (None, None, None)
    sim = drivesim.Simulator(plain, batch=2)
    z, h = np.zeros(plain.z_dim, np.float32), np.zeros(plain.hidden_dim, np.float32)
    with pytest.raises(ValueError, match="no reward head"):
        sim.reward(z, h)
    with pytest.raises(ValueError, match="no value head"):
        sim.value(z, h)
    with pytest.raises(ValueError, match="no pace head"):
        sim.pace(z, h)
    assert plain.pace_width is None
    with pytest.raises(ValueError, match="no reward head"):
        sim.rollout_candidates_scored(h, np.zeros((2, 2, 2), np.float32), z=z)
    with pytest.raises(ValueError, match="reward, value"):
        carracing.MPCAgent(model=plain)
    sim = drivesim.Simulator(model, batch=2)
    z, h = np.zeros(model.z_dim, np.float32), np.zeros(model.hidden_dim, np.float32)
    with pytest.raises(ValueError):
        sim.value(z, np.zeros((2, model.hidden_dim), np.float32))
    with pytest.raises(ValueError):
        sim.reward(np.full(model.z_dim, np.nan, np.float32), h)
    with pytest.raises(ValueError):
        sim.rollout_candidates_scored(h, np.zeros((2, 3, 2), np.float32), z=z)  # 3 candidates > batch 2
    with pytest.raises(ValueError):
        sim.rollout_candidates_scored(h, np.zeros((2, 2), np.float32))

"""The crate's Environment and the gymnasium environments of the dream."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import drivesim


def seeds_of(clip, drives, s=5):
    frames, actions = clip
    return (np.ascontiguousarray(np.stack([frames[:s]] * drives, axis=1)),
            np.ascontiguousarray(np.stack([actions[: s - 1]] * drives, axis=1)))


def test_environment_steps_like_the_simulator(model, clip):
    env = drivesim.Environment(model, drives=2, candidates=4)
    frames, actions = seeds_of(clip, 2)
    env.reset(frames, actions)
    sim = drivesim.Simulator(model)
    expected = sim.rollout(clip[0][:5], np.concatenate([clip[1][:4], [[30.0, -0.3]] * 2]).astype(np.float32))
    for t in range(2):
        env.step(np.float32([[30.0, -0.3], [30.0, 0.3]]))
        np.testing.assert_array_equal(env.codes[0], expected[t])
    assert env.hidden.shape == (2, 256)
    assert env.frames().shape == (2, 80, 160, 3)
    plan = np.zeros((3, 4, 2), np.float32) + np.float32([30.0, 0.0])
    assert env.rollout_candidates(1, plan).shape == (3, 4, 128)
    with pytest.raises(ValueError, match="drive"):
        env.rollout_candidates(2, plan)
    with pytest.raises(ValueError, match="2 drives"):
        env.step(np.zeros((3, 2), np.float32))


def test_environment_before_reset(model):
    env = drivesim.Environment(model, drives=1)
    with pytest.raises(ValueError, match="reset"):
        env.step(np.zeros((1, 2), np.float32))


def test_dream_env_passes_check_env():
    env = drivesim.DreamEnv(max_steps=20, render_mode="rgb_array")
    check_env(env, skip_render_check=False)


def test_dream_env_registered_and_deterministic():
    env = gymnasium.make("drivesim/Dream-v0", max_steps=5)
    runs = []
    for _ in range(2):
        obs, info = env.reset(seed=3)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(np.float32([35.0, 0.2]))
            total += reward
            done = terminated or truncated
        runs.append((obs, total))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1] and np.isfinite(runs[0][1])
    lo, hi = drivesim.action_bounds(drivesim.Model.load())
    assert env.action_space.low.tolist() == lo.tolist() and env.action_space.high.tolist() == hi.tolist()


def test_dream_env_resets_from_given_frames(clip):
    env = drivesim.DreamEnv()
    frames, actions = clip
    a, _ = env.reset(options={"frames": frames[:5], "actions": actions[:4]})
    b, _ = env.reset(options={"episode": 0, "start": 0})
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        env.step(np.float32([np.nan, 0.0]))
    with pytest.raises(ValueError, match="episode"):
        env.reset(options={"episode": 99})


def test_dream_vector_env(clip):
    envs = drivesim.DreamVectorEnv(3, max_steps=2)
    assert envs.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    obs, _ = envs.reset(seed=1)
    assert obs.shape == (3, 80, 160, 3) and obs in envs.observation_space
    single = drivesim.DreamEnv(max_steps=2)
    for t in range(2):
        obs, rewards, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert rewards.shape == (3,) and not terminated.any()
        assert truncated.all() == (t == 1)
    # The step after truncation resets every drive.
    obs, rewards, terminated, truncated, _ = envs.step(envs.action_space.sample())
    assert not rewards.any() and not truncated.any()
    # A drive of the vector env is the single env's drive, bit for bit.
    frames, actions = clip
    envs.reset(options={"frames": np.stack([frames[:5]] * 3, 1), "actions": np.stack([actions[:4]] * 3, 1)})
    single.reset(options={"frames": frames[:5], "actions": actions[:4]})
    a = np.float32([[30.0, 0.1]] * 3)
    vobs, vrew, *_ = envs.step(a)
    # Seed frames without the actions between them: zero actions.
    still, _ = envs.reset(options={"frames": np.stack([frames[:1]] * 3, 1)})
    assert still.shape == (3, 80, 160, 3)
    sobs, srew, *_ = single.step(a[0])
    np.testing.assert_array_equal(vobs[1], sobs)
    assert vrew[1] == srew

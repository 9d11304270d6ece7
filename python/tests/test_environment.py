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


def test_dream_env_learned_reward_is_the_heads():
    env = drivesim.DreamEnv(reward="learned", max_steps=5)
    env.reset(seed=3)
    sim = drivesim.Simulator(env.model)
    for _ in range(3):
        _, reward, _, _, info = env.step(np.array([40.0, 0.1], np.float32))
        head = sim.reward(env._env.codes, env._env.hidden)
        assert reward == float(head[0, 0]) and info["off_road"] == np.clip(head[0, 1], 0, 1)


def test_dream_env_takes_carracing_actions():
    # Gas, steering and brake move the dream as the (speed, steering) they stand for: the speed
    # the car reaches under speed_control, from the last seed action's speed. The dream is stepped
    # with the env's own speed (float32, rounded each step), checked against the float64 formula.
    from drivesim.carracing.control import speed_after

    racing = drivesim.DreamEnv(actions="carracing", max_steps=20)
    plain = drivesim.DreamEnv(max_steps=20)
    assert racing.action_space.shape == (3,) and check_env(racing, skip_render_check=True) is None
    _, info = racing.reset(seed=4)
    plain.reset(seed=4)
    speed = float(racing._speed[0])  # the last seed action's
    for steer, gas, brake in [(0.3, 0.6, 0.0), (-0.2, 0.0, 0.0), (0.0, 0.0, 0.5), (1.5, 2.0, -1.0), (0.0, 1.0, 0.3)]:
        stepped_with = racing._speed[0]
        assert stepped_with == pytest.approx(speed, abs=1e-4)
        obs, *_, info = racing.step(np.array([steer, gas, brake], np.float32))
        expected, *_ = plain.step(np.array([stepped_with, np.clip(steer, -1, 1)], np.float32))
        assert np.array_equal(obs, expected)
        gas, brake = np.clip(gas, 0, 1), np.clip(brake, 0, 1)
        # The brake wins where both are pressed (the last action: the real car stops).
        target = speed - 4 - brake / 0.06 if brake > 0 else (speed + gas / 0.06 if gas > 0 else speed)
        speed = float(np.clip(speed_after(speed, max(target, 0.0)), racing.low[0], racing.high[0]))
        assert info["speed"] == pytest.approx(speed, abs=1e-4)
    with pytest.raises(ValueError, match="shape"):
        racing.step(np.array([0.0, 40.0], np.float32))


def test_dream_env_ends_off_the_road():
    # Steering hard right with gas takes the dream's car off the road: the episode ends after
    # `off_road_steps` steps in a row there; driving straight it does not.
    env = drivesim.DreamEnv(actions="carracing", off_road_steps=3, max_steps=40)
    env.reset(seed=1)
    off, steps = 0, 0
    for steps in range(1, 41):
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.6, 0.0], np.float32))
        off = off + 1 if info["road"][3] < 0.5 else 0
        assert terminated == (off >= 3)
        if terminated or truncated:
            break
    assert terminated and steps < 40
    env.reset(seed=1)
    for _ in range(10):
        _, _, terminated, *_ = env.step(np.array([0.0, 0.2, 0.0], np.float32))
        assert not terminated


def test_dream_options_are_checked():
    for bad in [dict(reward="real"), dict(actions="keyboard"), dict(off_road_steps=0), dict(reward=1)]:
        with pytest.raises((ValueError, TypeError)):
            drivesim.DreamEnv(**bad)
    with pytest.raises(TypeError):
        drivesim.DreamVectorEnv(2, off_road_steps=3)


def test_dream_vector_env_learned_and_carracing():
    envs = drivesim.DreamVectorEnv(3, reward="learned", actions="carracing", max_steps=3)
    envs.reset(seed=0)
    single = drivesim.DreamEnv(reward="learned", actions="carracing", max_steps=3)
    _, rewards, _, _, info = envs.step(np.tile(np.array([0.1, 0.5, 0.0], np.float32), (3, 1)))
    assert rewards.shape == (3,) and info["off_road"].shape == (3,) and info["speed"].shape == (3,)
    assert envs.single_action_space.shape == (3,) and single.action_space.shape == (3,)


def test_dream_docstrings_run():
    import doctest

    import drivesim.dream

    failed, tried = doctest.testmod(drivesim.dream, raise_on_error=False)
    assert tried >= 10 and failed == 0

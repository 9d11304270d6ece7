"""Tests of the racing-pace expert (drivesim.carracing.expert) and of the rewards that episodes carry."""

import math

import numpy as np
import pytest

from drivesim import episodes

pytest.importorskip("Box2D")
from drivesim.carracing import expert  # noqa: E402 (after the skip: it needs Box2D)


def circle_track(radius, n=200):
    """CarRacing's track format, (beta, heading, x, y) per point, on a circle run anticlockwise."""
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return [(0.0, 0.0, radius * math.cos(a), radius * math.sin(a)) for a in t]


def test_curvature_and_speed_profile_of_a_circle():
    e = expert.Expert(circle_track(40.0))
    # Anticlockwise: turning left, curvature +1/R everywhere (the chords' bend, within 0.1 %).
    np.testing.assert_allclose(e.curvature, 1 / 40.0, rtol=1e-3)
    np.testing.assert_allclose(e.profile, math.sqrt(expert.LATERAL_ACCEL * 40.0), rtol=1e-3)
    mirrored = expert.Expert([(b, h, x, -y) for b, h, x, y in circle_track(40.0)])
    np.testing.assert_allclose(mirrored.curvature, -1 / 40.0, rtol=1e-3)


def test_speed_profile_brakes_in_time_for_a_bend():
    # A straight, then a tight bend: the profile falls before the bend at most as fast as the
    # brakes allow, and reaches the top speed far from it.
    curvature = np.zeros(300)
    curvature[200:220] = 0.1
    seg = np.full(300, 3.5)
    v = expert._speed_profile(curvature, seg)
    bend = math.sqrt(expert.LATERAL_ACCEL / 0.1)
    np.testing.assert_allclose(v[200:220], bend)
    assert v[100] == expert.TOP_SPEED
    assert np.all(v[:-1] ** 2 <= v[1:] ** 2 + 2 * expert.BRAKE_ACCEL * seg[:-1] + 1e-6)
    assert v[195] < expert.TOP_SPEED  # braking starts before the bend


def test_expert_is_deterministic_and_draws_no_random_numbers():
    from drivesim.carracing import record
    runs = []
    for rng_seed in (0, 1):
        env = record.car_racing.CarRacing()
        env.reset(seed=11)
        env._render = lambda *args, **kwargs: None  # the physics alone
        rng = np.random.default_rng(rng_seed)
        driver = record.Driver(env.track, rng, "expert")
        assert isinstance(driver, expert.Expert)
        actions = []
        for _ in range(60):
            action, _, _ = driver.act(env.car, 4 / record.car_racing.FPS)
            actions.append(action)
            for _ in range(4):
                env.step(action)
        env.close()
        runs.append(np.array(actions))
        assert rng.random() == np.random.default_rng(rng_seed).random()  # the rng untouched
    np.testing.assert_array_equal(runs[0], runs[1])
    assert runs[0][:, 1].max() > 0.9  # (nearly) full throttle on the way out of the start


def test_expert_finishes_a_lap_at_racing_pace():
    from drivesim.carracing import record
    # Seed 8000: one of the held-out evaluation tracks (922 in docs/carracing.md); a lap
    # finished in under 1000 frames scores over 900, an unfinished one under 900.
    assert record.score_episode(8000, "expert") > 900


def test_the_expert_held_to_a_top_speed_plans_under_it():
    """`record --score --top-speed V`: the same profile, clipped at V (the braking passes keep
    every later point reachable, so lowering the cap is clipping the profile)."""
    import gymnasium

    from drivesim.carracing import record
    from drivesim.carracing.expert import Expert

    env = gymnasium.make("CarRacing-v3").unwrapped
    env.reset(seed=8000)
    free, held = Expert(env.track), Expert(env.track, top_speed=45.0)
    assert free.profile.max() > 60.0 and held.profile.max() == 45.0
    np.testing.assert_allclose(held.profile, np.minimum(free.profile, 45.0))
    env.close()
    for bad in (["--top-speed", "60"], ["--score", "--driver", "steady", "--top-speed", "60"],
                ["--score", "--driver", "expert", "--top-speed", "5"]):
        with pytest.raises(SystemExit):
            record.main(["--seeds", "0"] + bad)
    with pytest.raises(ValueError, match="expert's"):
        record.score_episode(0, "steady", top_speed=60.0)


def test_recorded_episodes_carry_rewards(tmp_path):
    from drivesim.carracing import record
    frames, actions, _, rewards, labels = record.record_episode(seed=3, frames=30, frame_skip=4, style="expert")
    assert {k: (v.dtype, v.shape) for k, v in rewards.items()} == {
        "reward": (np.float32, (30,)), "tiles": (np.int32, (30,)), "on_road": (np.uint8, (30,))}
    assert rewards["on_road"].all() and rewards["tiles"].sum() > 10
    # Each decision's reward is its new tiles' share of 1000 less 0.1 a frame.
    new = rewards["tiles"] > 0
    per_tile = (rewards["reward"][new] + 0.4) / rewards["tiles"][new]
    assert np.ptp(per_tile) < 1e-2 and 2 < per_tile.mean() < 4  # 1000 / N, N about 300
    np.testing.assert_allclose(rewards["reward"][~new], -0.4, atol=1e-4)
    # The expert's labels: the speed it drove to (at least the speed it had, leaving the start)
    # and the steering it applied.
    assert labels.shape == (30, 2) and labels.dtype == np.float32
    np.testing.assert_array_equal(labels[:, 1], actions[:, 1])
    assert labels[0, 0] > actions[0, 0]
    path = tmp_path / "e.safetensors.gz"
    episodes.write(path, episodes.Episodes(frames, actions, np.array([0]), rewards, labels))
    back = episodes.read(path)
    np.testing.assert_array_equal(back.labels, labels)
    for k in episodes.REWARDS:
        np.testing.assert_array_equal(back.rewards[k], rewards[k])


def make(n=6, rewards=True):
    rng = np.random.default_rng(0)
    r = {"reward": rng.standard_normal(n).astype(np.float32), "tiles": np.arange(n, dtype=np.int32),
         "on_road": np.ones(n, np.uint8)} if rewards else None
    return episodes.Episodes(rng.integers(0, 256, (n, 8, 16, 3), dtype=np.uint8),
                             rng.standard_normal((n, 2)).astype(np.float32), np.array([0, 4]), r)


def test_rewards_follow_mirror_images_and_concat(tmp_path):
    e = make()
    m = e.with_mirror_images()
    np.testing.assert_array_equal(m.rewards["tiles"], np.concatenate([e.rewards["tiles"]] * 2))
    assert episodes.Episodes.concat([e, e]).rewards["reward"].shape == (12,)
    assert episodes.Episodes.concat([e, make(rewards=False)]).rewards is None  # all or none


def test_old_files_without_rewards_still_load(tmp_path):
    path = tmp_path / "old.safetensors"
    episodes.write(path, make(rewards=False))
    assert episodes.read(path).rewards is None


@pytest.mark.parametrize("bad, message", [
    ({"reward": np.zeros(6, np.float32)}, "must hold exactly"),
    ({"reward": np.zeros(6, np.float64), "tiles": np.zeros(6, np.int32), "on_road": np.zeros(6, np.uint8)},
     "reward must be float32"),
    ({"reward": np.full(6, np.nan, np.float32), "tiles": np.zeros(6, np.int32), "on_road": np.zeros(6, np.uint8)},
     "NaN"),
    ({"reward": np.zeros(6, np.float32), "tiles": -np.ones(6, np.int32), "on_road": np.zeros(6, np.uint8)},
     "negative"),
    ({"reward": np.zeros(5, np.float32), "tiles": np.zeros(5, np.int32), "on_road": np.zeros(5, np.uint8)},
     r"\[6\]"),
])
def test_bad_rewards_are_rejected(bad, message):
    e = make(rewards=False)
    with pytest.raises(episodes.EpisodesError, match=message):
        episodes.Episodes(e.frames, e.actions, e.episode_starts, bad)


def test_a_file_with_some_of_the_reward_tensors_is_rejected(tmp_path):
    from safetensors.numpy import save_file
    e = make(rewards=False)
    path = tmp_path / "part.safetensors"
    save_file({"frames": e.frames, "actions": e.actions, "episode_starts": e.episode_starts,
               "reward": np.zeros(6, np.float32)}, str(path))
    with pytest.raises(episodes.EpisodesError, match="all or none"):
        episodes.read(path)


def test_labels_round_trip_mirror_and_fill_in(tmp_path):
    e = make()
    labels = np.stack([np.full(6, 50.0), np.linspace(-0.5, 0.5, 6)], 1).astype(np.float32)
    taught = episodes.Episodes(e.frames, e.actions, e.episode_starts, e.rewards, labels)
    path = tmp_path / "l.safetensors"
    episodes.write(path, taught)
    np.testing.assert_array_equal(episodes.read(path).labels, labels)
    np.testing.assert_array_equal(taught.with_mirror_images().labels[6:, 1], -labels[:, 1])
    # Joined with unlabelled episodes: theirs are what `train policy` fits (speed 1 frame later).
    plain = make(rewards=False)
    joined = episodes.Episodes.concat([taught, plain])
    np.testing.assert_array_equal(joined.labels[:6], labels)
    np.testing.assert_array_equal(joined.labels[6:, 1], plain.actions[:, 1])
    np.testing.assert_array_equal(joined.labels[6:9, 0], plain.actions[1:4, 0])
    assert joined.labels[9, 0] == plain.actions[3, 0]  # the first episode's last frame: its own
    with pytest.raises(episodes.EpisodesError, match="labels hold NaN"):
        episodes.Episodes(e.frames, e.actions, e.episode_starts, None, np.full((6, 2), np.nan, np.float32))
    with pytest.raises(episodes.EpisodesError, match=r"labels must be float32 \[6,2\]"):
        episodes.Episodes(e.frames, e.actions, e.episode_starts, None, np.zeros((6, 3), np.float32))

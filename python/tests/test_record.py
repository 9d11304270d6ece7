"""The CarRacing recorder's scripted drivers (drivesim.carracing.record)."""

import numpy as np
import pytest

pytest.importorskip("Box2D")
from drivesim.carracing import record  # noqa: E402 (after the skip: it needs gymnasium's Box2D)


def test_record_short_episode():
    frames, actions, on_road, _, _ = record.record_episode(seed=3, frames=5, frame_skip=2)
    assert frames.shape == (5, 80, 160, 3) and frames.dtype == np.uint8
    assert actions.shape == (5, 2) and np.all(np.abs(actions[:, 1]) <= 1)
    assert 0 <= on_road <= 1
    assert record.parse_seeds("0-2,7") == [0, 1, 2, 7]


@pytest.mark.parametrize("style", ["varied", "varied-noise", "varied-holds", "holds", "hard", "jerky", "expert-holds", "expert-speeds"])
def test_record_driver_styles(style):
    frames, actions, _, _, _ = record.record_episode(seed=4, frames=40, frame_skip=2, style=style, random_colours=True)
    assert frames.shape == (40, 80, 160, 3) and np.all(np.abs(actions[:, 1]) <= 1)
    steady, _, _, _, _ = record.record_episode(seed=4, frames=1, frame_skip=2)
    # Random colours: the first frame (the car still at the start line) differs from the env's colours.
    assert np.abs(frames[0].astype(int) - steady[0]).mean() > 10


def test_jerky_driver_holds_its_steering_between_looks():
    _, actions, _, _, _ = record.record_episode(seed=5, frames=60, frame_skip=2, style="jerky")
    steering = actions[:, 1]
    held = steering[1:] == steering[:-1]
    # Looks every 0.12-0.3 s, frames 0.04 s apart: each steering value lasts 3 to 8 frames.
    assert 0.6 < held.mean() < 0.9
    changes = np.flatnonzero(~held)
    assert np.all(np.diff(changes) >= 3) and np.all(np.diff(changes) <= 8)


def test_varied_noise_driver_redraws_its_noise_level():
    from gymnasium.envs.box2d import car_racing

    env = car_racing.CarRacing()
    env.reset(seed=6)
    driver = record.Driver(env.track, np.random.default_rng(6), "varied-noise")
    env.close()
    levels = set()
    for _ in range(200):  # 200 frames of 0.08 s: manoeuvres last 1-4 s
        driver.lateral(0.08)
        levels.add(driver.steer_noise.sigma)
    assert len(levels) >= 4 and all(0.02 <= s <= 0.15 for s in levels)


def runs_of(values):
    """(length, value) of each run of equal consecutive values."""
    ends = [*np.flatnonzero(values[1:] != values[:-1]) + 1, len(values)]
    return [(end - start, values[start]) for start, end in zip([0, *ends[:-1]], ends)]


def test_varied_holds_driver_holds_constant_steering_open_loop():
    # A hold: 0.2-0.8 s of one steering of 0.1-0.7, whatever the road: 3 to 10 frames of 0.08 s
    # (11 when the seconds left round just above zero).
    def holds(style):
        _, actions, _, _, _ = record.record_episode(seed=7, frames=400, frame_skip=4, style=style)
        return [n for n, s in runs_of(actions[:, 1]) if n >= 3 and 0.1 <= abs(s) <= 0.7]

    held = holds("varied-holds")
    assert len(held) >= 3 and max(held) <= 11
    assert holds("varied") == []  # pure pursuit with coloured noise never repeats a steering
    # `holds`: a hold, then a recovery of 0.4-1.2 s and back to the road, again and again.
    many = holds("holds")
    assert len(many) >= 8 and max(many) <= 11 and 0.1 < sum(many) / 400 < 0.5


def test_expert_holds_driver_holds_at_racing_pace():
    # Holds of 0.05-0.3 for 0.2-0.5 s (3 to 7 frames of 0.08 s) between 1-3 s of the expert's own
    # driving, at the expert's pace: far faster than the slow `holds`. (Full lock held is the
    # expert's own steering, clipped, in a recovery.)
    _, actions, _, _, labels = record.record_episode(seed=8, frames=300, frame_skip=4, style="expert-holds")
    held = [(n, s) for n, s in runs_of(actions[:, 1]) if n >= 3 and abs(s) < 1]
    assert len(held) >= 6 and all(n <= 7 and 0.05 <= abs(s) <= 0.3 for n, s in held)
    _, slow, _, _, _ = record.record_episode(seed=8, frames=300, frame_skip=4, style="holds")
    assert actions[100:, 0].mean() > 1.5 * slow[100:, 0].mean() and labels is None


def test_expert_speeds_driver_takes_bends_too_fast_and_too_slow():
    # The expert's steering with its speed profile scaled by 0.6-1.7, redrawn every 1-3 s: on the
    # same track its speeds spread far wider than the expert's own, and the fast bends take the
    # car off the road, which the expert never leaves.
    _, actions, _, rewards, labels = record.record_episode(seed=7800, frames=300, frame_skip=4, style="expert-speeds")
    _, planned, _, kept, _ = record.record_episode(seed=7800, frames=300, frame_skip=4, style="expert")
    assert labels is None and kept["on_road"].all() and rewards["on_road"].mean() < 0.95
    assert actions[50:, 0].std() > 1.15 * planned[50:, 0].std()
    assert actions[50:, 0].min() < planned[50:, 0].min() - 5

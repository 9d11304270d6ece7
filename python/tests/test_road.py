"""The road measured on frames and predicted from codes."""

import numpy as np
import pytest

import drivesim
from drivesim import road


def synthetic(offset):
    """A grass frame with a vertical grey road whose centre is `offset` px right of the car."""
    f = np.zeros((1, 80, 160, 3), np.uint8)
    f[...] = (100, 200, 100)
    c = 80 + offset
    f[:, :, c - 15 : c + 15] = (105, 105, 105)
    return f


def test_measure_reads_the_offset():
    for offset in (-20, 0, 30):
        near, middle, far, under = road.measure(synthetic(offset))[0]
        assert abs(near - offset) < 1 and abs(far - offset) < 1
        assert under == (1.0 if abs(offset) < 10 else 0.0)
    with pytest.raises(ValueError):
        road.measure(np.zeros((80, 160, 3), np.float32))


def test_default_cost_reads_real_codes(model, clip):
    frames, _ = clip
    sim = drivesim.Simulator(model, batch=8)
    predicted = road.RoadCost.default().predict(sim.encode(frames))
    measured = road.measure(frames)
    assert np.abs(predicted[:, 0] - measured[:, 0]).mean() < 8  # pixels


def test_fit_save_load(tmp_path):
    rng = np.random.default_rng(0)
    codes = rng.standard_normal((200, 6)).astype(np.float32)
    figures = codes @ rng.standard_normal((6, 4)) + 1.0
    cost = road.RoadCost.fit(codes, figures, ridge=1e-6)
    assert np.allclose(cost.predict(codes), figures, atol=1e-3)
    cost.save(tmp_path / "c.npz")
    again = road.RoadCost.load(tmp_path / "c.npz")
    np.testing.assert_array_equal(again.predict(codes), cost.predict(codes))
    assert road.r_squared(cost, codes, figures).min() > 0.999


@pytest.mark.parametrize("lock", [0.5, 1.0])
@pytest.mark.parametrize("straight_first", [0, 8])
def test_the_default_world_moves_the_road_the_right_way_up_to_full_lock(model, clip, lock, straight_first):
    """The play page's check (tests/browser/play.py) without the browser: from the seed clip,
    `straight_first` decisions straight (the page drives on while the key is not yet down), then
    the steering ramped as the page ramps a held arrow (0.08 a frame, 37 frames) to `lock`. The
    road's centre, read before the road first leaves sight, lies right of the straight drive's
    after steering left and left of it after steering right. (Held full lock takes the real car
    round and the road back into sight from the other side: what follows its leaving is not read.)"""
    frames, actions = clip
    speed = float(actions[3, 0])
    sim = drivesim.Simulator(model, batch=1, threads=1)
    ends = {}
    for name, sign in (("straight", 0), ("left", -1), ("right", 1)):
        steer, ramp = 0.0, [(speed, 0.0)] * straight_first
        for _ in range(37):
            steer += float(np.clip(sign * lock - steer, -0.08, 0.08))
            ramp.append((speed, steer))
        _, dream = sim.rollout(frames[:5], np.concatenate([actions[:4], np.float32(ramp)]), frames=True)
        centres = [road.centre(f) for f in dream[straight_first:]]
        lost = next((i for i, c in enumerate(centres) if c is None), len(centres))
        assert lost >= 3, f"{name}: the road left sight at once ({centres})"
        ends[name] = float(np.mean(centres[lost - 3:lost]))
    assert ends["left"] > ends["straight"] + 10 > ends["right"] + 20, ends

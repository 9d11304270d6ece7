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

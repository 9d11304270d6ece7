"""drivesim.carracing.branches: paired steering branches from the same states."""

import numpy as np
import pytest

pytest.importorskip("Box2D")

from drivesim import episodes, probe  # noqa: E402
from drivesim.carracing import branches  # noqa: E402


def test_three_branches_from_each_point_share_its_past_and_part_by_their_steering(tmp_path):
    out = tmp_path / "b.safetensors.gz"
    assert branches.main(["--seeds", "3", "--frames", "30", "--every", "10", "--horizon", "3", "--workers", "1",
                          "--out", str(out)]) == 0
    data, meta = episodes.read(out), episodes.metadata(out)
    assert meta["branches"] == "3" and meta["driver"] == "hard" and meta["horizon"] == "3" and meta["seeds"] == "3"
    bounds = data.bounds()
    assert len(bounds) == 9 and all(e - s == probe.SEEDS + 3 for s, e in bounds)  # points at 9, 19, 29
    for k in range(0, len(bounds), 3):
        left, straight, right = (slice(*bounds[k + i]) for i in range(3))
        seeds = slice(0, probe.SEEDS)
        # The point's past is the drive's, the same in the three.
        np.testing.assert_array_equal(data.frames[left][seeds], data.frames[straight][seeds])
        np.testing.assert_array_equal(data.frames[right][seeds], data.frames[straight][seeds])
        np.testing.assert_array_equal(data.actions[left][:probe.SEEDS - 1], data.actions[right][:probe.SEEDS - 1])
        # From the point on, a constant steering: -x, 0, +x with x in its range.
        steer = [data.actions[s][probe.SEEDS - 1:, 1] for s in (left, straight, right)]
        x = steer[2][0]
        assert branches.STEER[0] <= x <= branches.STEER[1]
        for held, want in zip(steer, (-x, 0.0, x)):
            np.testing.assert_allclose(held, want, rtol=1e-6)
        # And the steering did something: the branches' last frames differ.
        assert not np.array_equal(data.frames[left][-1], data.frames[right][-1])
    assert set(data.rewards) == set(episodes.REWARDS)


def test_the_replayed_point_is_the_recorded_frame():
    drive = branches.base_drive(5, "hard", 20)
    episode, replayed = branches.branch(5, "hard", drive, 12, 0.4, 2)
    assert replayed == 0.0
    np.testing.assert_array_equal(episode.frames[probe.SEEDS - 1], drive["frames"][12])
    np.testing.assert_array_equal(episode.frames[:probe.SEEDS], np.stack(drive["frames"][8:13]))


def test_offset_branches_are_the_drivers_own_steering_moved_by_minus_x_0_plus_x(tmp_path):
    out = tmp_path / "o.safetensors.gz"
    assert branches.main(["--seeds", "3", "--frames", "20", "--every", "10", "--horizon", "4", "--workers", "1",
                          "--offsets", "--steer", "0.2,0.3", "--out", str(out)]) == 0
    data, meta = episodes.read(out), episodes.metadata(out)
    assert meta["kind"] == "offsets" and meta["steer"] == "0.2,0.3" and meta["branches"] == "3"
    drive = branches.base_drive(3, "hard", 20)
    bounds = data.bounds()
    assert len(bounds) == 6
    for k, point in ((0, 9), (3, 19)):
        left, straight, right = (data.actions[slice(*bounds[k + i])][probe.SEEDS - 1:, 1] for i in range(3))
        # The 0 branch is the driver itself: its first steering is the drive's.
        assert straight[0] == drive["actions"][point][1]
        x = right[0] - straight[0]
        assert 0.2 - 1e-6 <= x <= 0.3 + 1e-6 and abs(straight[0] - left[0] - x) < 1e-6
        # The driver keeps steering (it corrects), so the branch's steering is not held constant.
        assert np.ptp(straight) > 0.0 and np.ptp(right) > 0.0


def test_noise_branches_kick_the_drivers_own_steering_by_the_same_draws_either_way(tmp_path):
    out = tmp_path / "n.safetensors.gz"
    assert branches.main(["--seeds", "3", "--frames", "20", "--every", "10", "--horizon", "4", "--workers", "1",
                          "--noise", "--steer", "0.2,0.3", "--out", str(out)]) == 0
    data, meta = episodes.read(out), episodes.metadata(out)
    assert meta["kind"] == "noise" and meta["steer"] == "0.2,0.3"
    bounds = data.bounds()
    assert len(bounds) == 6
    rng = np.random.default_rng(3 + 1_000_003)  # the track's draws, as `track_branches` makes them
    kicks = []
    for k in (0, 3):
        x, noise = rng.uniform(0.2, 0.3), rng.standard_normal(5)
        left, straight, right = (data.actions[slice(*bounds[k + i])][probe.SEEDS - 1:, 1] for i in range(3))
        # At the point the three share the driver's own steering, moved by -x n_0, 0 and +x n_0.
        np.testing.assert_allclose(right[0], np.clip(straight[0] + x * noise[0], -1, 1), atol=1e-6)
        np.testing.assert_allclose(left[0], np.clip(straight[0] - x * noise[0], -1, 1), atol=1e-6)
        kicks.append(right[0] - straight[0])
    # A fresh draw at each point: the kicks are not one constant offset.
    assert kicks[0] != kicks[1] and np.sign(kicks[0]) in (-1.0, 1.0)


def test_clone_branches_are_driven_by_the_default_cloned_policy(tmp_path):
    out = tmp_path / "c.safetensors.gz"
    assert branches.main(["--seeds", "3", "--driver", "clone", "--frames", "20", "--every", "10", "--horizon", "3",
                          "--workers", "1", "--offsets", "--steer", "0.2,0.3", "--out", str(out)]) == 0
    data, meta = episodes.read(out), episodes.metadata(out)
    assert meta["driver"] == "clone" and meta["kind"] == "offsets"
    drive, hard = branches.base_drive(3, "clone", 20), branches.base_drive(3, "hard", 20)
    # The clone steers as the cloned policy does, not as the scripted driver.
    assert not np.allclose(np.array(drive["actions"])[:, 1], np.array(hard["actions"])[:, 1], atol=0.02)
    bounds = data.bounds()
    for k, point in ((0, 9), (3, 19)):
        left, straight, right = (data.actions[slice(*bounds[k + i])][probe.SEEDS - 1:, 1] for i in range(3))
        # Replayed to the point, the clone steers there as in its drive; the branches move it by -x, +x.
        assert straight[0] == drive["actions"][point][1]
        assert 0.2 - 1e-6 <= right[0] - straight[0] <= 0.3 + 1e-6


def test_offsets_and_noise_are_refused_together(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        branches.main(["--seeds", "3", "--offsets", "--noise", "--out", str(tmp_path / "b.safetensors.gz")])
    assert e.value.code == 2 and "not allowed with" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["0,0.5", "0.5,0.2", "0.2,1.5", "x", "0.2"])
def test_a_bad_steer_range_is_refused(tmp_path, capsys, bad):
    with pytest.raises(SystemExit) as e:
        branches.main(["--seeds", "3", "--steer", bad, "--out", str(tmp_path / "b.safetensors.gz")])
    assert e.value.code == 2 and "--steer" in capsys.readouterr().err
    assert not (tmp_path / "b.safetensors.gz").exists()


def test_a_drive_too_short_for_a_point_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        branches.main(["--seeds", "3", "--frames", "5", "--out", str(tmp_path / "b.safetensors.gz")])
    assert e.value.code == 2 and "leaves no branch point" in capsys.readouterr().err
    assert not (tmp_path / "b.safetensors.gz").exists()

"""Tests of the data tools: episodes format, comma converter, CarRacing recorder."""

import h5py
import numpy as np
import pytest

import convert_comma
import episodes


def make_episodes(n=6, starts=(0, 4)):
    rng = np.random.default_rng(0)
    return episodes.Episodes(
        rng.integers(0, 256, (n, 8, 16, 3), dtype=np.uint8),
        rng.standard_normal((n, 2)).astype(np.float32),
        np.array(starts, dtype=np.int64),
    )


@pytest.mark.parametrize("name", ["e.safetensors", "e.safetensors.gz"])
def test_episodes_round_trip(tmp_path, name):
    e = make_episodes()
    episodes.write(tmp_path / name, e, {"note": "x"})
    back = episodes.read(tmp_path / name)
    for k in ("frames", "actions", "episode_starts"):
        np.testing.assert_array_equal(getattr(back, k), getattr(e, k))
    assert back.bounds() == [(0, 4), (4, 6)]


@pytest.mark.parametrize("change, message", [
    (dict(starts=(1, 4)), "begin at 0"),
    (dict(starts=(0, 4, 4)), "strictly increasing"),
    (dict(starts=(0, 6)), "past the last frame"),
])
def test_episodes_reject_bad_starts(change, message):
    with pytest.raises(episodes.EpisodesError, match=message):
        make_episodes(**change)


def test_episodes_reject_bad_arrays():
    e = make_episodes()
    with pytest.raises(episodes.EpisodesError, match="uint8"):
        episodes.Episodes(e.frames.astype(np.float32), e.actions, e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match=r"\[6,2\]"):
        episodes.Episodes(e.frames, e.actions[:5], e.episode_starts)


def test_episodes_read_errors(tmp_path):
    with pytest.raises(episodes.EpisodesError, match="no such file"):
        episodes.read(tmp_path / "missing.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(episodes.EpisodesError, match="not a"):
        episodes.read(tmp_path / "junk.safetensors")


def write_drive(root, rows_per_frame, n_frames=10):
    """A synthetic camera/log pair. Frame f is filled with the value 10*f; every log row of
    frame f has speed f and steering 2*f, except one glitch row with steering 999."""
    (root / "camera").mkdir(exist_ok=True)
    (root / "log").mkdir(exist_ok=True)
    x = np.repeat(np.arange(n_frames, dtype=np.uint8) * 10, 3 * 160 * 320).reshape(n_frames, 3, 160, 320)
    ptr = np.concatenate([np.full(k, f, dtype=np.float64) for f, k in enumerate(rows_per_frame)])
    speed, steer = ptr.copy(), 2 * ptr
    steer[1] = 999.0  # glitch row in frame 0, dropped
    with h5py.File(root / "camera" / "d.h5", "w") as f:
        f["X"] = x
    with h5py.File(root / "log" / "d.h5", "w") as f:
        f["cam1_ptr"], f["speed"], f["steering_angle"] = ptr, speed, steer
    return root / "camera" / "d.h5"


def test_comma_aligns_through_cam1_ptr(tmp_path):
    # 4-6 rows per frame, and rows for frames 10 and 11 that do not exist.
    cam = write_drive(tmp_path, [5, 4, 6, 5, 5, 4, 6, 5, 5, 4, 5, 5])
    e = convert_comma.convert_drive(cam, min_frames=1)
    assert e.frames.shape == (10, 80, 160, 3)
    np.testing.assert_array_equal(e.frames[:, 0, 0, 0], np.arange(10) * 10)
    np.testing.assert_allclose(e.actions[:, 0], np.arange(10))
    np.testing.assert_allclose(e.actions[:, 1], 2 * np.arange(10))
    assert list(e.episode_starts) == [0]


def test_comma_splits_at_frames_without_rows(tmp_path):
    # Frame 4 has no log rows: two episodes, 0-3 and 5-9.
    cam = write_drive(tmp_path, [5, 5, 5, 5, 0, 5, 5, 5, 5, 5])
    e = convert_comma.convert_drive(cam, min_frames=1)
    assert list(e.episode_starts) == [0, 4]
    np.testing.assert_array_equal(e.frames[:, 0, 0, 0], [0, 10, 20, 30, 50, 60, 70, 80, 90])
    # A stride keeps every other frame of each episode; min_frames drops short ones.
    e = convert_comma.convert_drive(cam, stride=2, min_frames=3)
    np.testing.assert_allclose(e.actions[:, 0], [5, 7, 9])


def test_comma_downsample_averages_blocks():
    x = np.zeros((1, 3, 160, 320), dtype=np.uint8)
    x[0, 0, 0, 0] = 200  # one bright pixel of a 2x2 block -> a quarter of it
    x[0, 2] = 7
    y = convert_comma.downsample(x)
    assert y.shape == (1, 80, 160, 3)
    assert (y[0, 0, 0] == [50, 0, 7]).all()


def test_comma_errors(tmp_path):
    with pytest.raises(ValueError, match="'camera' folder"):
        convert_comma.convert_drive(tmp_path / "d.h5")
    cam = write_drive(tmp_path, [5] * 10)
    (tmp_path / "log" / "d.h5").unlink()
    with pytest.raises(FileNotFoundError, match="log/d.h5"):
        convert_comma.convert_drive(cam)
    with h5py.File(tmp_path / "log" / "d.h5", "w") as f:
        f["speed"] = np.zeros(3)
    with pytest.raises(ValueError, match="missing datasets"):
        convert_comma.convert_drive(cam)


def test_record_short_episode():
    record = pytest.importorskip("record")
    frames, actions, on_road = record.record_episode(seed=3, frames=5, frame_skip=2)
    assert frames.shape == (5, 80, 160, 3) and frames.dtype == np.uint8
    assert actions.shape == (5, 2) and np.all(np.abs(actions[:, 1]) <= 1)
    assert 0 <= on_road <= 1
    assert record.parse_seeds("0-2,7") == [0, 1, 2, 7]

"""The comma.ai research dataset converter (drivesim.comma; HDF5 through h5py)."""

import re

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")
from drivesim import comma, episodes  # noqa: E402 (after the skip: it needs h5py)


def write_drive(root, rows_per_frame, n_frames=10):
    """A synthetic camera/log pair. Frame f is filled with the value 10*f; every log row of
    frame f has speed f and steering 2*f, except one glitch row with steering 999."""
    (root / "camera").mkdir(parents=True, exist_ok=True)
    (root / "log").mkdir(parents=True, exist_ok=True)
    x = np.repeat(np.arange(n_frames, dtype=np.uint8) * 10, 3 * 160 * 320).reshape(n_frames, 3, 160, 320)
    ptr = np.concatenate([np.full(k, f, dtype=np.float64) for f, k in enumerate(rows_per_frame)])
    speed, steer = ptr.copy(), 2 * ptr
    steer[1] = 999.0  # glitch row in frame 0, dropped
    with h5py.File(root / "camera" / "d.h5", "w") as f:
        f["X"] = x
    with h5py.File(root / "log" / "d.h5", "w") as f:
        f["cam1_ptr"], f["speed"], f["steering_angle"] = ptr, speed, steer
    return root / "camera" / "d.h5"


def set_log(root, name, values):
    with h5py.File(root / "log" / "d.h5", "a") as f:
        del f[name]
        f[name] = values


def test_comma_aligns_through_cam1_ptr(tmp_path):
    # 4-6 rows per frame, and rows for frames 10 and 11 that do not exist.
    cam = write_drive(tmp_path, [5, 4, 6, 5, 5, 4, 6, 5, 5, 4, 5, 5])
    e = comma.convert_drive(cam, min_frames=1)
    assert e.frames.shape == (10, 80, 160, 3)
    np.testing.assert_array_equal(e.frames[:, 0, 0, 0], np.arange(10) * 10)
    np.testing.assert_allclose(e.actions[:, 0], np.arange(10))
    np.testing.assert_allclose(e.actions[:, 1], 2 * np.arange(10))
    assert list(e.episode_starts) == [0]


def test_comma_splits_at_frames_without_rows(tmp_path):
    # Frame 4 has no log rows: two episodes, 0-3 and 5-9.
    cam = write_drive(tmp_path, [5, 5, 5, 5, 0, 5, 5, 5, 5, 5])
    e = comma.convert_drive(cam, min_frames=1)
    assert list(e.episode_starts) == [0, 4]
    np.testing.assert_array_equal(e.frames[:, 0, 0, 0], [0, 10, 20, 30, 50, 60, 70, 80, 90])
    # A stride keeps every other frame of each episode; min_frames drops short ones.
    e = comma.convert_drive(cam, stride=2, min_frames=3)
    np.testing.assert_allclose(e.actions[:, 0], [5, 7, 9])


def test_comma_accepts_column_logs(tmp_path):
    # Log datasets stored as [R,1] convert exactly as [R] ones.
    flat = comma.convert_drive(write_drive(tmp_path / "a", [5] * 10), min_frames=1)
    cam = write_drive(tmp_path / "b", [5] * 10)
    for name in ("cam1_ptr", "speed", "steering_angle"):
        with h5py.File(tmp_path / "b" / "log" / "d.h5", "r") as f:
            column = f[name][:][:, None]
        set_log(tmp_path / "b", name, column)
    e = comma.convert_drive(cam, min_frames=1)
    np.testing.assert_array_equal(e.frames, flat.frames)
    np.testing.assert_array_equal(e.actions, flat.actions)


@pytest.mark.parametrize("name, shape", [
    ("cam1_ptr", (50, 2)), ("speed", (25, 2)), ("steering_angle", (50, 1, 1)), ("speed", ()),
])
def test_comma_rejects_bad_log_shapes(tmp_path, name, shape):
    cam = write_drive(tmp_path, [5] * 10)
    set_log(tmp_path, name, np.zeros(shape))
    message = f"log/d.h5: {name} must be [R] or [R,1], got {shape}"
    with pytest.raises(ValueError, match=re.escape(message)):
        comma.convert_drive(cam, min_frames=1)


def test_comma_main_checks_every_input_first(tmp_path, capsys):
    # A bad log in the second drive stops the run before the first drive is converted,
    # with one line on stderr and exit status 2.
    good = write_drive(tmp_path / "a", [5] * 10)
    bad = write_drive(tmp_path / "b", [5] * 10)
    set_log(tmp_path / "b", "cam1_ptr", np.zeros((50, 2)))
    with pytest.raises(SystemExit) as exit_:
        comma.main([str(good), str(bad), "--min-frames", "1", "--out", str(tmp_path / "e.safetensors")])
    assert exit_.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith("python -m drivesim convert-comma: error: ") and "cam1_ptr" in err and err.count("\n") == 1


def test_comma_main_out_folder(tmp_path, capsys):
    cam = write_drive(tmp_path, [5] * 10)
    with pytest.raises(SystemExit) as exit_:
        comma.main([str(cam), "--min-frames", "1", "--out", str(tmp_path / "missing" / "e.safetensors")])
    assert exit_.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""  # nothing was converted
    assert err == f"python -m drivesim convert-comma: error: --out {tmp_path / 'missing' / 'e.safetensors'}: " \
                  f"folder {tmp_path / 'missing'} does not exist\n"
    comma.main([str(cam), "--min-frames", "1", "--out", str(tmp_path / "e.safetensors")])
    assert len(episodes.read(tmp_path / "e.safetensors").frames) == 10


def test_comma_downsample_averages_blocks():
    x = np.zeros((1, 3, 160, 320), dtype=np.uint8)
    x[0, 0, 0, 0] = 200  # one bright pixel of a 2x2 block -> a quarter of it
    x[0, 2] = 7
    y = comma.downsample(x)
    assert y.shape == (1, 80, 160, 3)
    assert (y[0, 0, 0] == [50, 0, 7]).all()


def test_comma_errors(tmp_path):
    with pytest.raises(ValueError, match="'camera' folder"):
        comma.convert_drive(tmp_path / "d.h5")
    cam = write_drive(tmp_path, [5] * 10)
    (tmp_path / "log" / "d.h5").unlink()
    with pytest.raises(FileNotFoundError, match="log/d.h5"):
        comma.convert_drive(cam)
    with h5py.File(tmp_path / "log" / "d.h5", "w") as f:
        f["speed"] = np.zeros(3)
    with pytest.raises(ValueError, match="missing datasets"):
        comma.convert_drive(cam)
    write_drive(tmp_path, [5] * 10)
    set_log(tmp_path, "speed", np.zeros(40))
    with pytest.raises(ValueError, match="log/d.h5: log datasets differ in length"):
        comma.convert_drive(cam)

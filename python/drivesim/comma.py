"""Convert comma.ai research dataset drives into an episodes file (see drivesim.episodes).

The dataset keeps each drive as a pair of HDF5 files with the same name:
  camera/NAME.h5  X              uint8 [N, 3, 160, 320]  frames at 20 Hz
  log/NAME.h5     speed          [R] m/s                 sensor rows at 100 Hz
                  steering_angle [R] degrees
                  cam1_ptr       [R] camera frame index of each row
The three log datasets may also be [R,1].
Each frame gets the mean speed and steering of the log rows that point at it. Rows with
|steering_angle| > 200 are dropped, as in the dataset's own loader; rows pointing past the
last frame are ignored. Frames left without a row split the drive into separate episodes,
so every episode is continuous in time. Steering stays in degrees, speed in m/s.

  python -m drivesim convert-comma camera/2016-01-30--11-24-51.h5 ... --stride 4 --out comma.safetensors.gz
"""

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np

from . import episodes

LOG_KEYS = ("cam1_ptr", "speed", "steering_angle")
MAX_STEERING = 200.0  # degrees; larger values are sensor glitches
CHUNK = 512  # frames read at a time, so a multi-GB camera file never sits in memory


def log_path(camera_path):
    p = Path(camera_path)
    if p.parent.name != "camera":
        raise ValueError(f"{p}: expected a file inside a 'camera' folder (its log is in ../log/)")
    return p.parent.parent / "log" / p.name


def check_drive(camera_path):
    """Check a drive's files, datasets and shapes without reading the data, so that bad input
    fails before any conversion. Returns the log's path."""
    camera_path = Path(camera_path)
    logp = log_path(camera_path)
    for p in (camera_path, logp):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
    with h5py.File(logp, "r") as log:
        missing = [k for k in LOG_KEYS if k not in log]
        if missing:
            raise ValueError(f"{logp}: missing datasets {missing}")
        shapes = {k: log[k].shape for k in LOG_KEYS}
    for k, shape in shapes.items():
        if not (len(shape) == 1 or (len(shape) == 2 and shape[1] == 1)):
            raise ValueError(f"{logp}: {k} must be [R] or [R,1], got {shape}")
    if len({shape[0] for shape in shapes.values()}) > 1:
        raise ValueError(f"{logp}: log datasets differ in length: "
                         + ", ".join(f"{k} {shape[0]}" for k, shape in shapes.items()))
    with h5py.File(camera_path, "r") as cam:
        if "X" not in cam:
            raise ValueError(f"{camera_path}: missing dataset X")
        x = cam["X"]
        if x.ndim != 4 or x.shape[1:] != (3, 160, 320) or x.dtype != np.uint8:
            raise ValueError(f"{camera_path}: X must be uint8 [N,3,160,320], got {x.dtype} {x.shape}")
    return logp


def frame_actions(n_frames, cam1_ptr, speed, steering):
    """Per-frame (speed, steering) means over the log rows pointing at each frame; the three
    log vectors are [R]. Returns actions [n_frames, 2] float32 and a mask of frames that had
    at least one row."""
    ptr = np.floor(np.asarray(cam1_ptr, dtype=np.float64)).astype(np.int64)
    speed = np.asarray(speed, dtype=np.float64)
    steering = np.asarray(steering, dtype=np.float64)
    keep = (ptr >= 0) & (ptr < n_frames) & (np.abs(steering) <= MAX_STEERING) \
        & np.isfinite(speed) & np.isfinite(steering)
    ptr = ptr[keep]
    count = np.bincount(ptr, minlength=n_frames)
    has = count > 0
    actions = np.zeros((n_frames, 2), dtype=np.float64)
    for col, values in enumerate((speed[keep], steering[keep])):
        actions[has, col] = np.bincount(ptr, weights=values, minlength=n_frames)[has] / count[has]
    return actions.astype(np.float32), has


def downsample(x):
    """[n, 3, 160, 320] uint8 -> [n, 80, 160, 3] by averaging 2x2 blocks."""
    n, c, h, w = x.shape
    blocks = x.reshape(n, c, h // 2, 2, w // 2, 2).astype(np.uint16).sum(axis=(3, 5))
    return ((blocks + 2) // 4).astype(np.uint8).transpose(0, 2, 3, 1)


def runs(mask):
    """(start, end) of each run of True in a boolean vector."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def convert_drive(camera_path, stride=1, min_frames=15):
    """Episodes from one drive, or None if no run of frames is long enough."""
    logp = check_drive(camera_path)
    with h5py.File(logp, "r") as log:
        # check_drive allowed [R] and [R,1] only, so flattening cannot mix rows.
        cam1_ptr, speed, steering = (log[k][:].reshape(-1) for k in LOG_KEYS)
    with h5py.File(camera_path, "r") as cam:
        x = cam["X"]
        actions, has = frame_actions(len(x), cam1_ptr, speed, steering)
        parts = []
        for start, end in runs(has):
            idx = np.arange(start, end, stride)
            if len(idx) < min_frames:
                continue
            frames = np.concatenate([downsample(x[i:min(i + CHUNK * stride, end):stride])
                                     for i in range(start, end, CHUNK * stride)])
            parts.append(episodes.Episodes(frames, actions[idx], np.zeros(1, dtype=np.int64)))
    return episodes.Episodes.concat(parts) if parts else None


def fail(message):
    """One line on stderr and exit status 2, as argparse does for bad arguments."""
    print(f"python -m drivesim convert-comma: error: {message}", file=sys.stderr)
    sys.exit(2)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("camera", nargs="+", help="camera/NAME.h5 files (their logs are read from log/NAME.h5)")
    p.add_argument("--stride", type=int, default=1, help="keep every STRIDE-th frame (4 gives 5 Hz)")
    p.add_argument("--min-frames", type=int, default=15, help="drop episodes shorter than this")
    p.add_argument("--out", required=True,
                   help="episodes file (.safetensors or .safetensors.gz); its folder must already exist")
    args = p.parse_args(argv)
    if args.stride < 1 or args.min_frames < 1:
        p.error("--stride and --min-frames must be positive")

    # Every input and the output folder are checked before the first drive is converted.
    out = Path(args.out)
    if not out.parent.is_dir():
        fail(f"--out {out}: folder {out.parent} does not exist")
    if out.is_dir():
        fail(f"--out {out} is a folder")
    try:
        for path in args.camera:
            check_drive(path)
    except (OSError, ValueError) as e:
        fail(e)

    parts = []
    for path in args.camera:
        try:
            drive = convert_drive(path, args.stride, args.min_frames)
        except (OSError, ValueError) as e:  # ValueError includes episodes.EpisodesError
            fail(e)
        n = 0 if drive is None else len(drive.frames)
        print(f"{path}: {n} frames in {0 if drive is None else len(drive)} episodes")
        if drive is not None:
            parts.append(drive)
    if not parts:
        fail("no episode of at least --min-frames frames")
    data = episodes.Episodes.concat(parts)
    try:
        episodes.write(out, data, {"source": "comma.ai research dataset", "units": "m/s, degrees",
                                   "frame_hz": str(20 / args.stride)})
    except OSError as e:
        fail(e)
    print(f"wrote {args.out}: {len(data)} episodes, {len(data.frames)} frames")


if __name__ == "__main__":
    main()

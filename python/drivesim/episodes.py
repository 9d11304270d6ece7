"""Episodes file: recorded driving as one safetensors file.

Tensors (see the "Episodes format" section of weights/TRAINING_FILES.md):
  frames          uint8   [N, H, W, 3]  RGB frames, episodes back to back
  actions         float32 [N, 2]        (speed, steering) in effect at frame i
  episode_starts  int64   [E]           index of each episode's first frame; starts at 0, increasing
Optional, all three or none (recorded CarRacing, per decision: what a reward model learns from):
  reward          float32 [N]           the env's reward over the frames from frame i to frame i+1
  tiles           int32   [N]           track tiles first visited over those frames
  on_road         uint8   [N]           1 if a wheel touched the road at frame i, else 0
Optional (DAgger):
  labels          float32 [N, 2]        a teacher's (speed to drive at, steering) for frame i
"""

import gzip
import json
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
try:
    from safetensors.numpy import load
except ImportError as error:  # an extra, not a dependency of the simulator
    raise ImportError("drivesim.episodes needs safetensors: pip install 'drivesim[data]'") from error

from . import _files


class EpisodesError(ValueError):
    """An episodes file or array set that breaks the format."""


REWARDS = {"reward": np.float32, "tiles": np.int32, "on_road": np.uint8}  # the optional tensors


@dataclass
class Episodes:
    frames: np.ndarray
    actions: np.ndarray
    episode_starts: np.ndarray
    rewards: Optional[dict] = None  # {name: [N] array} for every name of REWARDS, or None
    labels: Optional[np.ndarray] = None  # [N, 2] float32, or None

    def __post_init__(self):
        self.frames = as_array(self.frames, np.uint8, "frames")
        self.actions = as_array(self.actions, np.float32, "actions")
        self.episode_starts = as_array(self.episode_starts, np.int64, "episode_starts")
        validate(self.frames, self.actions, self.episode_starts)
        if self.rewards is not None:
            self.rewards = validate_rewards(self.rewards, len(self.frames))
        if self.labels is not None:
            self.labels = as_array(self.labels, np.float32, "labels")
            if self.labels.dtype != np.float32 or self.labels.shape != (len(self.frames), 2):
                raise EpisodesError(f"labels must be float32 [{len(self.frames)},2], got "
                                    f"{self.labels.dtype} {list(self.labels.shape)}")
            if not np.isfinite(self.labels).all():
                raise EpisodesError("labels hold NaN or inf")

    def labelled(self, lead=1):
        """These episodes with labels: their own where they have them, else what `train
        policy` fits without labels, the speed `lead` frames later (the episode's last speed
        past its end) and the steering applied."""
        if self.labels is not None:
            return self
        labels = self.actions.copy()
        for s, e in self.bounds():
            later = np.minimum(np.arange(s, e) + lead, e - 1)
            labels[s:e, 0] = self.actions[later, 0]
        return Episodes(self.frames, self.actions, self.episode_starts, self.rewards, labels)

    def __len__(self):
        return len(self.episode_starts)

    def bounds(self):
        """(start, end) frame range of each episode."""
        ends = list(self.episode_starts[1:]) + [len(self.frames)]
        return [(int(s), int(e)) for s, e in zip(self.episode_starts, ends)]

    def windows(self, length):
        """Start indices of every run of `length` frames inside one episode."""
        runs = [np.arange(s, e - length + 1) for s, e in self.bounds() if e - s >= length]
        return np.concatenate(runs) if runs else np.zeros(0, np.int64)

    def with_mirror_images(self):
        """These episodes followed by their mirror images: every frame flipped left to right,
        the steering (the second action) negated, as the drive on the mirrored track would be
        (the Rust trainers' `--no-mirror` default, examples/common.rs `encode_view`)."""
        actions = self.actions.copy()
        actions[:, 1] *= -1
        rewards = None if self.rewards is None else {k: np.concatenate([v, v]) for k, v in self.rewards.items()}
        labels = None
        if self.labels is not None:
            labels = self.labels.copy()
            labels[:, 1] *= -1
            labels = np.concatenate([self.labels, labels])
        return Episodes(np.concatenate([self.frames, self.frames[:, :, ::-1]]),
                        np.concatenate([self.actions, actions]),
                        np.concatenate([self.episode_starts, self.episode_starts + len(self.frames)]),
                        rewards, labels)

    def episode(self, i):
        s, e = self.bounds()[i]
        return self.frames[s:e], self.actions[s:e]

    @staticmethod
    def concat(parts):
        """Join episode sets into one, shifting each part's starts. The rewards are kept only
        if every part has them; labels if any part has them (the others' `labelled()`)."""
        if not parts:
            raise EpisodesError("nothing to concatenate")
        offsets = np.cumsum([0] + [len(p.frames) for p in parts[:-1]])
        rewards = None
        if all(p.rewards is not None for p in parts):
            rewards = {k: np.concatenate([p.rewards[k] for p in parts]) for k in REWARDS}
        labels = None
        if any(p.labels is not None for p in parts):
            labels = np.concatenate([p.labelled().labels for p in parts])
        return Episodes(
            np.concatenate([p.frames for p in parts]),
            np.concatenate([p.actions for p in parts]),
            np.concatenate([p.episode_starts + o for p, o in zip(parts, offsets)]),
            rewards,
            labels,
        )


def as_array(x, dtype, name):
    """Lists (and other array-likes) become arrays of the format's dtype, if no value changes.
    An ndarray is passed through as is: a wrong dtype there is a caller's bug, left to validate()."""
    if isinstance(x, np.ndarray):
        return x
    try:
        a = np.asarray(x)
    except ValueError as e:  # ragged nested lists
        raise EpisodesError(f"{name}: not a regular array ({e})") from e
    if a.dtype.kind not in "iuf":
        raise EpisodesError(f"{name} must be numbers, got {type(x).__name__} of {a.dtype}")
    with np.errstate(invalid="ignore"):  # NaN to int: caught by the comparison below
        b = a.astype(dtype)
    if b.dtype.kind != "f" and not np.array_equal(a, b):
        raise EpisodesError(f"{name}: values do not fit {b.dtype}")
    return b


def validate(frames, actions, starts):
    def need(ok, what):
        if not ok:
            raise EpisodesError(what)

    need(frames.dtype == np.uint8, f"frames must be uint8, got {frames.dtype}")
    need(frames.ndim == 4 and frames.shape[3] == 3, f"frames must be [N,H,W,3], got {frames.shape}")
    need(len(frames) > 0, "no frames")
    need(actions.dtype == np.float32, f"actions must be float32, got {actions.dtype}")
    need(actions.shape == (len(frames), 2), f"actions must be [{len(frames)},2], got {actions.shape}")
    need(np.isfinite(actions).all(), "actions hold NaN or inf")
    need(starts.dtype == np.int64, f"episode_starts must be int64, got {starts.dtype}")
    need(starts.ndim == 1 and len(starts) > 0, "episode_starts must be a non-empty vector")
    need(starts[0] == 0, "episode_starts must begin at 0")
    need(bool(np.all(np.diff(starts) > 0)), "episode_starts must be strictly increasing")
    need(starts[-1] < len(frames), "an episode starts past the last frame")


def validate_rewards(rewards, n):
    """The optional per-decision tensors, checked and in their dtypes: all of REWARDS, each [n]."""
    if not isinstance(rewards, dict) or set(rewards) != set(REWARDS):
        got = sorted(rewards) if isinstance(rewards, dict) else type(rewards).__name__
        raise EpisodesError(f"rewards must hold exactly {sorted(REWARDS)}, got {got}")
    out = {}
    for name, dtype in REWARDS.items():
        a = as_array(rewards[name], dtype, name)
        if a.dtype != dtype or a.shape != (n,):
            raise EpisodesError(f"{name} must be {np.dtype(dtype).name} [{n}], got {a.dtype} {list(a.shape)}")
        if name == "reward" and not np.isfinite(a).all():
            raise EpisodesError("reward holds NaN or inf")
        if name != "reward" and (a < 0).any():
            raise EpisodesError(f"{name} must not be negative")
        out[name] = a
    return out


def sort_metadata(blob: bytes) -> bytes:
    """A safetensors file's bytes with its header's `__metadata__` in key order. safetensors
    writes it in a hash map's order, which changes from one save to the next: sorted, the same
    tensors and metadata are the same bytes (the crate's `weights::sort_metadata` is the twin)."""
    n = int.from_bytes(blob[:8], "little")
    header = json.loads(blob[8:8 + n])  # dicts keep the tensors' order
    if "__metadata__" not in header:
        return blob
    header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
    text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
    assert len(text) <= n, "the same header, reordered, is no longer"
    return blob[:8] + text.ljust(n) + blob[8 + n:]


#: safetensors' data order: the Rust crate sorts tensors by dtype, widest first, then by name.
_DTYPES = {np.dtype(np.int64): ("I64", 3), np.dtype(np.float32): ("F32", 2),
           np.dtype(np.int32): ("I32", 1), np.dtype(np.uint8): ("U8", 0)}


def _stream_safetensors(f, tensors, metadata):
    """`tensors` written to the binary file `f` as `sort_metadata(safetensors.numpy.save(...))`
    would write them, byte for byte, without building the file in memory: `save` holds three
    copies of the data at once (the arrays, their bytes, the file), which a 190,000-frame join
    (7.3 GB of frames) does not fit in 24 GB. Tested against `save` in test_episodes.py."""
    order = sorted(tensors, key=lambda k: (-_DTYPES[tensors[k].dtype][1], k))
    header, offset = {}, 0
    if metadata:
        header["__metadata__"] = dict(sorted(metadata.items()))
    for name in order:
        a = tensors[name]
        header[name] = {"dtype": _DTYPES[a.dtype][0], "shape": list(a.shape),
                        "data_offsets": [offset, offset + a.nbytes]}
        offset += a.nbytes
    text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
    text = text.ljust(-(-len(text) // 8) * 8)  # safetensors pads the header with spaces to 8 bytes
    f.write(len(text).to_bytes(8, "little") + text)
    for name in order:
        f.write(memoryview(np.ascontiguousarray(tensors[name])).cast("B"))


def write(path, episodes, metadata=None):
    """Save episodes; a path ending in .gz is gzipped. metadata: optional str->str header dict.
    Atomic: a temporary file beside `path`, flushed to disk and renamed over it, so a crash or a
    full disk leaves the old file whole (the package's `atomic_write`). Streamed: the file is
    never built in memory (a strided array, a mirror image's frames, is copied to be written)."""
    tensors = {"frames": episodes.frames, "actions": episodes.actions,
               "episode_starts": episodes.episode_starts, **(episodes.rewards or {})}
    if episodes.labels is not None:
        tensors["labels"] = episodes.labels
    path = Path(path)
    with _files.atomic_write(path) as f:
        if path.suffix == ".gz":
            z = _Gzip(f)
            _stream_safetensors(z, tensors, metadata)
            z.close()
        else:
            _stream_safetensors(f, tensors, metadata)


class _Gzip:
    """Writes `gzip.compress(data, 6, mtime=0)` of the data written to it, in pieces: zlib's
    gzip stream, no name and no time stamp, so the same data are the same bytes."""

    def __init__(self, f):
        self.f, self.z = f, zlib.compressobj(6, zlib.DEFLATED, 31)

    def write(self, data):
        self.f.write(self.z.compress(data))

    def close(self):
        self.f.write(self.z.flush())


def _blob(path):
    path = Path(path)
    if not path.is_file():
        raise EpisodesError(f"{path}: no such file")
    blob = path.read_bytes()
    try:
        return gzip.decompress(blob) if path.suffix == ".gz" else blob
    except Exception as e:
        raise EpisodesError(f"{path}: not a (gzipped) safetensors file ({e})") from e


def metadata(path):
    """The str->str metadata of an episodes file (`source`, `seeds`, `frame_hz`, ...), {} if none.
    Reads only the safetensors header (an 8-byte little-endian length, then that much JSON), so a
    gzipped file is not decompressed past it."""
    path = Path(path)
    if not path.is_file():
        raise EpisodesError(f"{path}: no such file")
    try:
        with (gzip.open if path.suffix == ".gz" else open)(path, "rb") as f:
            size = int.from_bytes(f.read(8), "little")
            if size > 100_000_000:  # safetensors' own limit on a header
                raise ValueError(f"a header of {size} bytes")
            header = json.loads(f.read(size))
        return dict(header.get("__metadata__") or {})
    except Exception as e:
        raise EpisodesError(f"{path}: not a (gzipped) safetensors file ({e!r})") from e


def read(path):
    blob = _blob(path)
    try:
        tensors = load(blob)
    except Exception as e:  # safetensors raises several types for a bad header
        raise EpisodesError(f"{path}: not a (gzipped) safetensors file ({e})") from e
    missing = {"frames", "actions", "episode_starts"} - tensors.keys()
    if missing:
        raise EpisodesError(f"{path}: missing tensors {sorted(missing)}")
    present = [k for k in REWARDS if k in tensors]
    if present and len(present) != len(REWARDS):
        raise EpisodesError(f"{path}: has {present} of the optional {list(REWARDS)}: all or none")
    rewards = {k: tensors[k] for k in present} or None
    try:
        return Episodes(tensors["frames"], tensors["actions"], tensors["episode_starts"], rewards,
                        tensors.get("labels"))
    except EpisodesError as e:
        raise EpisodesError(f"{path}: {e}") from e


def join(paths, out):
    """The episodes of ``paths``, in order, written to ``out`` as one file (rewards kept only if
    every file has them, labels if any: ``Episodes.concat``). The held-out episodes a trainer
    takes from the end (``--holdout N``) are then the last file's last ones. Returns the joined
    ``Episodes``. The metadata every file has alike is kept (a frame rate, `python -m drivesim
    branches`' layout), with ``source`` (theirs, joined by " + ") and ``joined`` (their names)."""
    data = Episodes.concat([read(p) for p in paths])
    metas = [metadata(p) for p in paths]
    shared = {k: v for k, v in metas[0].items() if all(m.get(k) == v for m in metas[1:])}
    sources = [m.get("source", Path(p).name) for m, p in zip(metas, paths)]
    write(out, data, {**shared, "source": " + ".join(sources), "joined": ",".join(Path(p).name for p in paths)})
    return data


def main(argv=None):
    """``python -m drivesim join --out OUT IN...``: episodes files joined into one."""
    import argparse

    p = argparse.ArgumentParser(description="Join episodes files into one, in the order given.")
    p.add_argument("inputs", nargs="+", help="episodes files (.safetensors or .safetensors.gz)")
    p.add_argument("--out", required=True, help="the joined file (.gz: gzipped)")
    args = p.parse_args(argv)
    try:
        data = join(args.inputs, args.out)
    except (EpisodesError, OSError) as e:
        p.exit(2, f"{p.prog}: error: {e}\n")
    print(f"wrote {args.out}: {len(data.episode_starts)} episodes, {len(data.frames)} frames")
    return 0

"""A sampler whose read-out is widened: the world's mean code spread further about a centre.

A transition trained on squared error predicts the mean of the next code, and a mean is narrower
than the codes it averages: dreamt from a drive's own states through the judge's sampler as it
was, the default's codes spread 0.6 times as far as the real ones about their mean. A driver
reads less of a car's place across the road off a narrow code, so it corrects a steady pull less
in the dream than on the road, and the pull rests further out (docs/history/widened.md).
``widen`` writes a sampler file (``drivesim.sampler``) that keeps a sampler's texture net and
carries a read-out of its own, the world's ``z' = A h' + a`` widened by ``BY`` about ``mu``, the
mean code of recorded drives (their frames and mirror images, encoded by the world)::

    z' = mu + BY * (A h' + a - mu),  so  A' = BY * A,  a' = BY * a + (1 - BY) * mu

``Model.load(world, sampler=FILE)`` then dreams the widened mean and the sampler's futures about
it; ``BY`` 1 gives the sampler's own read-out back. The built-in judge is the shipped
``judge.safetensors`` widened so (``Model.judge()``)::

    python -m drivesim widen weights/judge.safetensors --world weights/default.safetensors \\
        --about fh.safetensors.gz --by 1.03 --out judge.safetensors

>>> import drivesim
>>> drivesim.Model.judge().texture_width
256
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile

import numpy as np

from . import episodes as episodes_io
from ._drivesim import Model, Simulator, sampler_file
from .sampler import write_sampler_bytes

__all__ = ["mean_code", "widened_sampler", "write_widened"]

#: Frames encoded a call: the simulator's planned batch.
BATCH = 256


def mean_code(world: str | os.PathLike, about: str | os.PathLike) -> np.ndarray:
    """The mean code ``(z_dim,)`` of the frames of the episodes file ``about`` and of their mirror
    images (``Episodes.with_mirror_images``), encoded by the world of ``world``."""
    frames = episodes_io.read(about).frames
    if not len(frames):
        raise ValueError(f"{about}: no frames to take a mean code of")
    sim = Simulator(Model.load(world), batch=BATCH)
    total = 0.0
    for i in range(0, len(frames), BATCH):
        chunk = frames[i:i + BATCH]
        for view in (chunk, chunk[:, :, ::-1]):
            total = total + sim.encode(np.ascontiguousarray(view)).astype(np.float64).sum(0)
    return total / (2 * len(frames))


def widened_sampler(sampler: str | os.PathLike, world: str | os.PathLike, centre: np.ndarray, by: float) -> bytes:
    """The bytes of a sampler file with ``sampler``'s texture net and the read-out of ``world``
    widened by ``by`` about ``centre``, in the world's dtype (ValueError for a sampler of another
    world, a ``by`` that is not a positive finite number, a centre of another size, or a bf16
    world, which numpy cannot hold)."""
    from safetensors import safe_open
    from safetensors.numpy import load_file, save_file

    if not (isinstance(by, (int, float)) and math.isfinite(by) and by > 0):
        raise ValueError(f"by: expected a positive finite number, got {by!r}")
    Model.load(world, sampler=sampler)  # the crate's checks: a sampler, and learnt for this world
    try:
        tensors, own = load_file(os.fspath(world)), load_file(os.fspath(sampler))
    except TypeError as e:  # safetensors' numpy side has no bfloat16
        raise ValueError(f"{world} or {sampler}: {e}") from e
    big_a, small_a = (tensors[name].astype(np.float64) for name in ("transition.A", "transition.a"))
    if np.shape(centre) != small_a.shape or not np.all(np.isfinite(centre)):
        raise ValueError(f"centre: expected {small_a.shape[0]} finite values")
    dtype = tensors["transition.a"].dtype  # a weight file has one dtype; the sampler file takes it
    tensors.update({name: t.astype(dtype) for name, t in own.items()})
    tensors["transition.A"] = (by * big_a).astype(dtype)
    tensors["transition.a"] = (by * small_a + (1.0 - by) * np.asarray(centre, np.float64)).astype(dtype)
    with safe_open(os.fspath(world), "np") as f:
        metadata = f.metadata()
    with tempfile.TemporaryDirectory() as folder:  # the crate writes the sampler file from a whole world
        whole = os.path.join(folder, "widened.safetensors")
        save_file(tensors, whole, metadata=metadata)
        return sampler_file(whole, world)


def write_widened(sampler, world, about, by: float, out) -> str:
    """Writes ``widened_sampler`` about ``about``'s mean code to ``out``, atomically, and returns
    the world's fingerprint."""
    return write_sampler_bytes(widened_sampler(sampler, world, mean_code(world, about), by), world, out)


def main(argv=None) -> int:
    """``python -m drivesim widen SAMPLER --world W --about EPISODES --by BY --out FILE``."""
    p = argparse.ArgumentParser(prog="python -m drivesim widen", description=(
        "Write a sampler file with SAMPLER's texture net and the world's read-out widened by BY about "
        "the mean code of EPISODES' frames and their mirror images: z' = mu + BY (A h' + a - mu)."))
    p.add_argument("sampler", help="a sampler file learnt for the world (e.g. weights/judge.safetensors)")
    p.add_argument("--world", required=True, help="the world's weight file (e.g. weights/default.safetensors)")
    p.add_argument("--about", required=True, help="an episodes file: its mean code is the centre")
    p.add_argument("--by", type=float, required=True, help="how much wider: 1.03 for the judge, 1 the world's own")
    p.add_argument("--out", required=True, help="the sampler file to write (.safetensors)")
    args = p.parse_args(argv)
    if not (math.isfinite(args.by) and args.by > 0):
        p.error(f"--by: expected a positive number, got {args.by}")
    try:
        fingerprint = write_widened(args.sampler, args.world, args.about, args.by, args.out)
    except (OSError, ValueError) as e:  # EpisodesError is a ValueError
        p.exit(2, f"{p.prog}: error: {e}\n")
    print(f"wrote {args.out}: a sampler with its read-out widened {args.by}x, for world {fingerprint}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Sampler files: a texture net apart from the world whose transition it was learnt for
(``weights/README.md``).

``weights/tool train latent --freeze-transition`` writes the whole world (15 MB for the default)
with a new texture net: the same mean dream, other sampled futures. Its sampler file is that net
alone (260 kB) and the fingerprint of the world it was learnt for, so that
``Model.load(world, sampler=FILE)`` dreams that world's futures through it, and another world
refuses it (ValueError). Where the weight file's read-out (``transition.A``, ``transition.a``) is
not the world's, the sampler file carries it too, and the mean dream is the file's
(``drivesim.widen`` writes such a one). The package builds one in, the judge's: ``Model.judge()``,
whose futures rank drivers as the real track does (``python -m drivesim.carracing.rank --judge``).

>>> import drivesim
>>> judge, own = drivesim.Model.judge(), drivesim.Model.load()
>>> judge.texture_width, own.texture_width
(256, 256)
"""

from __future__ import annotations

import argparse
import os

from ._drivesim import sampler_file, world_fingerprint
from ._files import atomic_write

__all__ = ["sampler_file", "write_sampler", "write_sampler_bytes"]


def write_sampler(weights: str | os.PathLike, world: str | os.PathLike, out: str | os.PathLike) -> str:
    """Writes the sampler file of ``weights``'s texture net (and read-out, where it is not the
    world's) for ``world`` (a weight file that is the same world but for those; ValueError
    otherwise) to ``out``, atomically, and returns that world's fingerprint."""
    return write_sampler_bytes(sampler_file(weights, world), world, out)


def write_sampler_bytes(data: bytes, world: str | os.PathLike, out: str | os.PathLike) -> str:
    """Writes a sampler file's bytes ``data`` to ``out``, atomically, and returns the fingerprint
    of ``world``, the world they were written for."""
    with atomic_write(out) as f:
        f.write(data)
    return world_fingerprint(world)


def main(argv=None) -> int:
    """``python -m drivesim sampler WEIGHTS --world W --out FILE``."""
    p = argparse.ArgumentParser(prog="python -m drivesim sampler", description=(
        "Write the sampler file of a weight file's texture net (weights/tool train latent --freeze-transition "
        "writes one) for the world it was learnt for: the net and that world's fingerprint. "
        "Model.load(world, sampler=FILE) dreams through it."))
    p.add_argument("weights", help="a weight file with the texture net")
    p.add_argument("--world", required=True,
                   help="the world it was learnt for: the same weight file but for its texture net (e.g. the default's)")
    p.add_argument("--out", required=True, help="the sampler file to write (.safetensors)")
    args = p.parse_args(argv)
    try:
        fingerprint = write_sampler(args.weights, args.world, args.out)
    except (OSError, ValueError) as e:
        p.exit(2, f"{p.prog}: error: {e}\n")
    print(f"wrote {args.out}: a sampler learnt for world {fingerprint}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

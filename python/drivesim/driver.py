"""Driver files: a driver apart from the world it was learnt in (``weights/README.md``).

A weight file that ``weights/tool train driver`` writes is the whole world (15 MB for the
default) with the learnt driver as its policy. Its driver file is that policy alone (50 kB) and
the fingerprint of the world, so that ``Model.load(world, driver=FILE)`` drives it, and a world
it was not learnt in refuses it (ValueError) rather than driving codes the driver cannot read.

>>> import drivesim
>>> model = drivesim.Model.dreamt()   # the default world and the driver learnt in its dream
>>> model.policy_width, model.pace_width
(64, None)
"""

from __future__ import annotations

import argparse
import os

from ._drivesim import driver_file, world_fingerprint
from ._files import atomic_write

__all__ = ["driver_file", "world_fingerprint", "write_driver"]


def write_driver(weights: str | os.PathLike, out: str | os.PathLike, world: str | os.PathLike | None = None) -> str:
    """Writes the driver file of ``weights`` (a weight file whose policy is a learnt driver) to
    ``out``, atomically, and returns its world's fingerprint. With ``world``, a weight file, the
    driver must have been learnt in that world (ValueError otherwise)."""
    fingerprint = world_fingerprint(weights)
    expected = fingerprint if world is None else world_fingerprint(world)
    if expected != fingerprint:
        raise ValueError(f"{weights} holds another world than {world} ({fingerprint} against "
                         f"{expected}): its driver was not learnt there")
    data = driver_file(weights)
    with atomic_write(out) as f:
        f.write(data)
    return fingerprint


def main(argv=None) -> int:
    """``python -m drivesim driver WEIGHTS --out FILE [--world W]``."""
    p = argparse.ArgumentParser(prog="python -m drivesim driver", description=(
        "Write the driver file of a weight file whose policy is a learnt driver (weights/tool train driver "
        "writes one): its policy and the fingerprint of its world. Model.load(world, driver=FILE) drives it; "
        "make_agent('dreamt', weights=WORLD, driver=FILE) too."))
    p.add_argument("weights", help="a weight file whose policy is the driver")
    p.add_argument("--out", required=True, help="the driver file to write (.safetensors)")
    p.add_argument("--world", help="a weight file the driver must have been learnt in (e.g. the default's)")
    args = p.parse_args(argv)
    try:
        fingerprint = write_driver(args.weights, args.out, args.world)
    except (OSError, ValueError) as e:
        p.exit(2, f"{p.prog}: error: {e}\n")
    print(f"wrote {args.out}: a driver learnt in world {fingerprint}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

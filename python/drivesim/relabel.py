"""A policy carried to another world model: episodes labelled with a teacher model's policy.

A policy reads the transition's hidden state, so a world model whose transition was trained
again (on failure data, say: docs/judging.md) cannot keep the old policy as it is: on the new
hidden state the old weights drive worse. This labels every frame of an episodes file with what
the teacher's policy decides there (the teacher's encoder and transition stepped along each
episode from zeros with the recorded actions, as `train policy` steps the student's); `train
policy` then learns those labels on the new model's hidden state, as it learns DAgger's:

  python -m drivesim relabel data/failures.safetensors.gz --out data/labelled.safetensors.gz \\
      [--teacher weights/default.safetensors]
  cargo run --release --features train --example train -- policy --weights world.safetensors \\
      --episodes data/labelled.safetensors.gz --holdout 6 --out world_with_policy.safetensors

`--pace` labels the speed with the teacher's pace head instead, for `train policy --pace`.

Labels already in the file are replaced; everything else is kept as it is.
"""

import argparse
import os
import sys

import numpy as np

from . import _checks, episodes
from ._batches import batched
from ._drivesim import Model, Simulator


def labels(teacher: Model, data: episodes.Episodes, threads: int = 1, batch: int = 64,
           pace: bool = False) -> np.ndarray:
    """``(frames, 2)`` float32: the teacher policy's (speed to drive at, steering in [-1, 1]) at
    every frame of ``data``, its hidden state stepped from zeros at each episode's start. With
    ``pace`` the speed is its pace head's (``Simulator.pace``), the labels ``train policy --pace``
    learns."""
    if teacher.policy_width is None:
        raise ValueError("the teacher has no policy (policy.* tensors) to label with")
    if _checks.flag("pace", pace) and teacher.pace_width is None:
        raise ValueError("the teacher has no pace head (pace.* tensors) to label with")
    threads, batch = _checks.integer("threads", threads, 1), _checks.integer("batch", batch, 1)
    encoder = Simulator(teacher, batch=batch, threads=threads)
    z = batched(encoder.encode, data.frames, batch)
    out = np.zeros((len(z), 2), np.float32)
    step = Simulator(teacher, batch=1)
    for start, end in data.bounds():
        h = np.zeros(teacher.hidden_dim, np.float32)
        for t in range(start, end):
            out[t] = step.act(z[t], h)
            if pace:
                out[t, 0] = step.pace(z[t], h)[0]
            _, h = step.transition(z[t], h, data.actions[t])
    out[:, 1] = np.clip(out[:, 1], -1.0, 1.0)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim relabel", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("episodes", help="episodes file to label (.safetensors or .safetensors.gz)")
    p.add_argument("--out", required=True, help="the labelled file")
    p.add_argument("--teacher", help="weight file whose policy labels (default: the built-in model)")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="threads that encode the frames")
    p.add_argument("--pace", action="store_true",
                   help="the speed labels from the teacher's pace head (train policy --pace)")
    args = p.parse_args(argv)
    if args.threads < 1:
        p.error("--threads must be positive")
    try:
        teacher = Model.load(args.teacher)
        data = episodes.read(args.episodes)
        data.labels = labels(teacher, data, threads=args.threads, pace=args.pace)
        source = f"the {'pace head and steering' if args.pace else 'policy'} of {args.teacher or 'the built-in model'}"
        episodes.write(args.out, data, {**episodes.metadata(args.episodes), "labels": source})
    except (OSError, ValueError) as e:  # EpisodesError is a ValueError
        p.exit(2, f"{p.prog}: error: {e}\n")
    print(f"wrote {args.out}: {len(data.frames)} frames in {len(data.episode_starts)} episodes labelled")
    return 0


if __name__ == "__main__":
    sys.exit(main())

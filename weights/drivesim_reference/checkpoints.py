"""Checkpoints of `train fit` (--checkpoint FILE --checkpoint-every N --resume): everything the
run needs to go on as if it had never stopped. A resumed run writes the `--out` bytes of the
run that never stopped, on the same device and number of processes (the tests check it on the
CPU, in one process and under torchrun).

The file is `torch.save` of a dict (weights/TRAINING_FILES.md, "Checkpoints"): `format`, `arguments`
(those that decide the run), `stage` ("vae_gan" or "transition") and `step` (steps of it done),
`model` and `discriminator` (state dicts), `optimisers` (the stage's Adam states) and
`scheduler` (the transition's learning-rate schedule), `random` (the global generators', the
VAE-GAN's batch order's, the transition's window order's), `log` and `seconds` (the VAE-GAN's
time so far, for --max-minutes). Every process holds the same weights, optimiser states and
generators (each draws the global batch and takes its share), so the first process writes it,
atomically, and every process reads it."""

import io
import os

import numpy as np
import torch

from drivesim import _files
from drivesim_reference.distributed import world

FORMAT = "drivesim train.py fit checkpoint 1"
# Arguments that do not change what the run computes: a resumed run may change them (the
# written file's dtype and its noise factor's power are applied after the last step).
FREE = {"out", "dtype", "device", "log_every", "max_minutes", "checkpoint", "checkpoint_every", "resume", "mode",
        "noise_power"}


def run_arguments(args) -> dict:
    """The arguments that decide the run, as strings (as the log states them)."""
    return {k: str(v) for k, v in sorted(vars(args).items()) if k not in FREE}


class Checkpoints:
    """Where a run writes its checkpoints, how often, and whether it resumes from one."""

    def __init__(self, args, device: torch.device):
        self.path, self.every, self.resume = args.checkpoint, args.checkpoint_every, args.resume
        self.arguments, self.device = run_arguments(args), device
        if self.every < 1:
            raise ValueError("--checkpoint-every must be at least 1")
        if self.resume and not self.path:
            raise ValueError("--resume needs --checkpoint FILE")

    def restore(self) -> dict | None:
        """The checkpoint to go on from (with --resume, where the file exists), else None. A file
        that is not one, or a checkpoint of a run with other arguments, is a ValueError."""
        if not (self.resume and os.path.exists(self.path)):
            return None
        try:
            state = torch.load(self.path, map_location=self.device, weights_only=True)
        except Exception as e:  # torch.load raises many kinds for a file that is not a checkpoint
            raise ValueError(f"{self.path}: not a checkpoint to resume from: {e}") from e
        if not isinstance(state, dict) or state.get("format") != FORMAT:
            raise ValueError(f"{self.path}: not a checkpoint to resume from: not of the format '{FORMAT}'")
        if state["arguments"] != self.arguments:
            differ = sorted(k for k in set(state["arguments"]) | set(self.arguments)
                            if state["arguments"].get(k) != self.arguments.get(k))
            theirs = ", ".join(f"{k}={state['arguments'].get(k)}" for k in differ)
            ours = ", ".join(f"{k}={self.arguments.get(k)}" for k in differ)
            raise ValueError(f"{self.path}: a checkpoint of a run with other arguments ({theirs}, not {ours})")
        return state

    def due(self, step: int, steps: int) -> bool:
        """Whether a checkpoint is due after `step` of a stage's `steps` (not after its last:
        the stage's end has its own)."""
        return bool(self.path) and step < steps and step % self.every == 0

    def save(self, stage, step, model, discriminator, log, optimisers=(), scheduler=None,
             batches=None, windows=None, seconds=0.0):
        """Writes the checkpoint (the first process; the others hold the same state)."""
        if not self.path or (world() > 1 and torch.distributed.get_rank()):
            return
        state = dict(format=FORMAT, arguments=self.arguments, stage=stage, step=step,
                     model=model.state_dict(), discriminator=discriminator.state_dict(),
                     optimisers=[o.state_dict() for o in optimisers],
                     scheduler=scheduler.state_dict() if scheduler else None,
                     random=random_states(batches, windows), log=list(log), seconds=seconds)
        buffer = io.BytesIO()
        torch.save(state, buffer)
        with _files.atomic_write(self.path) as f:
            f.write(buffer.getbuffer())

    def remove_leftovers(self):
        """The temporary files of saves a kill interrupted (atomic_write's), at a run's start."""
        if self.path:
            _files.remove_leftovers(self.path)


def random_states(batches: torch.Generator | None, windows: np.random.Generator | None) -> dict:
    states = dict(torch=torch.get_rng_state())
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        states["cuda"] = torch.cuda.get_rng_state()
    if batches is not None:
        states["batches"] = batches.get_state()
    if windows is not None:
        states["windows"] = windows.bit_generator.state
    return states


def restore_random(state: dict, batches: torch.Generator | None = None, windows: np.random.Generator | None = None):
    """Puts the generators back where the checkpoint `state` had them."""
    states = state["random"]
    torch.set_rng_state(states["torch"].cpu())
    if "cuda" in states:
        torch.cuda.set_rng_state(states["cuda"].cpu())
    if batches is not None:
        batches.set_state(states["batches"].cpu())
    if windows is not None:
        windows.bit_generator.state = states["windows"]

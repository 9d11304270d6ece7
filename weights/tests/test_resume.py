"""`train fit --checkpoint --resume`: a run killed at random moments and resumed each time writes
the bytes of the run that never stopped, in one process and under torchrun (weights/tool -m pytest)."""

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from drivesim_reference import train

# weights/: the package drivesim_reference runs from here whether or not it is installed.
HERE = Path(__file__).resolve().parents[1]
TWO_PROCESSES = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]


def fit_args(data, vae_steps, transition_steps):
    return ["fit", "--data", str(data), "--device", "cpu", "--base-channels", "2", "--z-dim", "4",
            "--hidden-dim", "6", "--vae-steps", str(vae_steps), "--batch", "4", "--transition-steps",
            str(transition_steps), "--transition-batch", "4", "--log-every", "50", "--dtype", "f32"]


def start(launcher, args):
    # A session of its own, so that no signal of the test's reaches the run but the kill.
    return subprocess.Popen([*launcher, "-m", "drivesim_reference.train", *args], cwd=HERE, env=dict(os.environ, OMP_NUM_THREADS="1"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)


def finish(launcher, args):
    run = start(launcher, args)
    _, err = run.communicate(timeout=600)
    # Under torchrun the failing worker's traceback may come well before the launcher's summary.
    lines = err.decode().splitlines()
    first = next((i for i, line in enumerate(lines) if "Traceback" in line or "Error" in line), len(lines))
    assert run.returncode == 0, "\n".join(lines[max(first - 5, 0):first + 40] + ["..."] + lines[-20:])


def kill_after_a_checkpoint(launcher, args, checkpoint, stage, rng):
    """Starts the run and SIGKILLs it at a random moment after it wrote a checkpoint of its own
    in `stage`. Returns whether the kill came before the run ended."""
    seen = checkpoint.stat().st_mtime_ns if checkpoint.exists() else None
    run = start(launcher, args)
    while run.poll() is None:
        if checkpoint.exists() and checkpoint.stat().st_mtime_ns != seen:
            seen = checkpoint.stat().st_mtime_ns
            if torch.load(checkpoint, weights_only=True)["stage"] == stage:
                break
        time.sleep(0.005)
    time.sleep(rng.uniform(0, 0.3))
    killed = run.poll() is None
    kill_tree(run.pid)
    run.wait()
    return killed


def kill_tree(pid):
    """SIGKILLs `pid` and every process under it, as a power cut would, and waits until they are
    gone. torchrun starts each worker in a session of its own: killing the launcher's process
    group left the workers running, still writing checkpoints beside the resumed run (the
    flaky failures of this test on two processes)."""
    tree = [pid]
    for parent in tree:
        tree += children(parent)
    for p in tree:
        try:
            os.kill(p, signal.SIGKILL)
        except ProcessLookupError:
            pass
    for p in tree[1:]:  # the launcher is the test's child: run.wait() reaps it
        while alive(p):
            time.sleep(0.005)


def children(pid):
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def alive(pid):
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def check_kills_and_resumes(launcher, data, tmp_path, kills, vae_steps, transition_steps):
    """The run killed once in each stage of `kills` (in order) and resumed each time, then
    finished: its --out is the bytes of the run that never stopped."""
    args = fit_args(data, vae_steps, transition_steps)
    whole, resumed, checkpoint = tmp_path / "whole.safetensors", tmp_path / "resumed.safetensors", tmp_path / "ck"
    finish(launcher, args + ["--out", str(whole)])
    resuming = args + ["--out", str(resumed), "--checkpoint", str(checkpoint), "--checkpoint-every", "5", "--resume"]
    rng, stopped_in = random.Random(3), []
    for stage in kills:
        assert kill_after_a_checkpoint(launcher, resuming, checkpoint, stage, rng), "the run ended before the kill"
        # Whatever the kill interrupted, the checkpoint left behind loads.
        stopped_in.append(torch.load(checkpoint, weights_only=True)["stage"])
    assert stopped_in == kills
    finish(launcher, resuming)
    assert resumed.read_bytes() == whole.read_bytes()
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]


def test_a_killed_fit_resumes_to_the_same_bytes(tiny_episodes, tmp_path):
    stages = ["vae_gan", "vae_gan", "transition", "transition"]
    check_kills_and_resumes([sys.executable], tiny_episodes, tmp_path, stages, vae_steps=60, transition_steps=300)


def test_a_killed_fit_on_two_processes_resumes_to_the_same_bytes(tiny_episodes, tmp_path):
    check_kills_and_resumes(TWO_PROCESSES, tiny_episodes, tmp_path, ["vae_gan", "transition"], vae_steps=40,
                            transition_steps=300)


def test_a_checkpoint_of_another_run_is_refused(tiny_episodes, tmp_path, capsys):
    checkpoint = tmp_path / "ck"
    args = fit_args(tiny_episodes, 4, 4) + ["--out", str(tmp_path / "m.safetensors"), "--checkpoint", str(checkpoint),
                                   "--checkpoint-every", "2"]
    train.main(args)
    before = checkpoint.read_bytes()
    other = list(args)
    other[other.index("--z-dim") + 1] = "5"
    with pytest.raises(SystemExit) as stop:
        train.main(other + ["--resume"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "a checkpoint of a run with other arguments (z_dim=4, not z_dim=5)" in err and str(checkpoint) in err
    assert checkpoint.read_bytes() == before
    checkpoint.write_bytes(b"not a checkpoint")
    with pytest.raises(SystemExit):
        train.main(args + ["--resume"])
    assert "not a checkpoint to resume from" in capsys.readouterr().err


def test_leftovers_of_killed_saves_are_removed(tiny_episodes, tmp_path):
    checkpoint = tmp_path / "ck"
    leftover, other = tmp_path / ".tmp-abc_123x-ck", tmp_path / ".tmp-abc_123x-other-ck"
    leftover.write_bytes(b"half a checkpoint")
    other.write_bytes(b"another file's")
    train.main(fit_args(tiny_episodes, 2, 2) + ["--out", str(tmp_path / "m.safetensors"), "--checkpoint", str(checkpoint)])
    assert not leftover.exists() and other.exists()

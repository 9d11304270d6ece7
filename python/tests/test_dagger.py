"""DAgger end to end (drivesim.carracing.dagger): a short round, and its resume after a kill. Needs the drivesim
package with CarRacing and the trainer (`cargo build --release -p drivesim-examples --features
train --example train`): skipped without them."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivesim import episodes

pytest.importorskip("Box2D")
from drivesim.carracing import record  # noqa: E402 (after the skip: it needs Box2D)

TRAINER = Path(__file__).resolve().parents[2] / "target/release/examples/train"
if not TRAINER.exists():
    pytest.skip("no trainer built (cargo build --release -p drivesim-examples --features train --example train)",
                allow_module_level=True)


@pytest.fixture(scope="module")
def expert_data(tmp_path_factory):
    frames, actions, _, rewards, labels = record.record_episode(seed=3, frames=40, frame_skip=4, style="expert")
    path = tmp_path_factory.mktemp("expert") / "expert.safetensors"
    episodes.write(path, episodes.Episodes(frames, actions, np.array([0, 20]), rewards, labels), {"frame_hz": "12.5"})
    return path


def command(data, out):
    return [sys.executable, "-m", "drivesim", "dagger", "--trainer", str(TRAINER), "--base", str(TRAINER.parents[3] / "weights/default.safetensors"), "--data", str(data), "--rounds", "1",
            "--tracks", "4000", "--per-round", "1", "--heldout", "5000", "--frames", "100", "--steps", "30",
            "--holdout", "1", "--workers", "1", "--dir", str(out)]


def test_a_short_round_end_to_end_and_its_resume_after_a_kill(expert_data, tmp_path):
    whole = tmp_path / "whole"
    subprocess.run(command(expert_data, whole), check=True, stdout=subprocess.DEVNULL)
    log = [json.loads(t) for t in (whole / "log.jsonl").read_text().splitlines()]
    assert [e["round"] for e in log] == [0, 1] and all(e["tracks"] == 1 for e in log)
    data = episodes.read(whole / "round_1" / "data.safetensors.gz")
    # 25 decisions in 100 frames, the agent's 12 warm-up decisions left out.
    assert len(data.frames) == 13 and data.labels is not None and data.rewards is not None
    assert np.all(data.labels[:, 0] > 0) and np.all(np.abs(data.labels[:, 1]) <= 1)
    # Killed at some moment, then started again: the same files as the run never stopped.
    killed = tmp_path / "killed"
    for wait in (6.0, 14.0):
        proc = subprocess.Popen(command(expert_data, killed), stdout=subprocess.DEVNULL, start_new_session=True)
        time.sleep(wait)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    subprocess.run(command(expert_data, killed), check=True, stdout=subprocess.DEVNULL)
    for name in ("round_0/policy.safetensors", "round_1/data.safetensors.gz", "round_1/policy.safetensors"):
        assert (killed / name).read_bytes() == (whole / name).read_bytes(), name
    assert (killed / "log.jsonl").read_text().count("\n") == 2


def test_steering_noise_is_a_seeded_ar1_sequence_of_its_deviation():
    from drivesim.carracing import dagger
    from itertools import islice
    assert list(islice(dagger.steering_noise(0.0, 4), 50)) == [0.0] * 50
    draws = np.array(list(islice(dagger.steering_noise(0.1, 4), 20000)))
    assert np.array_equal(draws[:100], np.array(list(islice(dagger.steering_noise(0.1, 4), 100))))
    assert not np.array_equal(draws[:100], np.array(list(islice(dagger.steering_noise(0.1, 5), 100))))
    assert abs(draws.std() - 0.1) < 0.01
    assert abs(np.corrcoef(draws[1:], draws[:-1])[0, 1] - dagger.NOISE_CORRELATION) < 0.03


def test_noise_moves_the_applied_and_recorded_steering_by_the_offset():
    from drivesim.carracing import dagger
    weights = Path(__file__).resolve().parents[2] / "weights/default.safetensors"
    plain, _ = dagger.drive_labelled((weights, 4000, 100, 0.0))
    noisy, _ = dagger.drive_labelled((weights, 4000, 100, 0.3))
    first = next(dagger.steering_noise(0.3, 4000))
    # The first recorded decision is the same state in both drives; only the offset differs.
    assert np.array_equal(plain.frames[0], noisy.frames[0])
    assert noisy.actions[0, 1] == pytest.approx(np.clip(plain.actions[0, 1] + first, -1, 1), abs=1e-6)
    # Later states differ: the car went where the perturbed steering took it.
    assert not np.array_equal(plain.frames[-1], noisy.frames[-1])
    assert np.array_equal(plain.labels.shape, noisy.labels.shape)

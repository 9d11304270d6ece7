"""`train.py steering` (train_steering.py): the transition fine-tuned on paired branches. It trains
the transition's step and keeps every other tensor, a stopped run goes on to the same bytes, the
effect term teaches what the steering did between a point's branches, and a file that is not
`python -m drivesim branches`' is refused."""

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from drivesim_reference.model import DriveSim, save_drivesim
from drivesim_reference.train_steering import effect_error
from test_heads import ACTIONS, HEAD_CFG, reward_episodes
from test_latent import TRANSITION
from test_texture import assert_resumes_to_the_same_bytes


def branch_file(path, points=2, length=7, metadata=True, seed=0):
    """Random 16x32 frames in three branches a point, `length` frames each: the first 5 shared,
    then steering -x, 0 and +x (as `python -m drivesim branches` writes them)."""
    from drivesim import episodes

    rng = np.random.default_rng(seed)
    frames, actions = [], []
    for _ in range(points):
        past = rng.integers(0, 256, (5, 16, 32, 3), dtype=np.uint8)
        x = rng.uniform(0.15, 0.7)
        for steer in (-x, 0.0, x):
            frames.append(np.concatenate([past, rng.integers(0, 256, (length - 5, 16, 32, 3), dtype=np.uint8)]))
            a = np.tile(np.float32([20.0, steer]), (length, 1))
            a[:4, 1] = 0.1
            actions.append(a)
    data = episodes.Episodes(np.concatenate(frames), np.concatenate(actions), np.arange(0, 3 * points * length, length))
    episodes.write(path, data, {"branches": "3"} if metadata else None)
    return path


def run(weights, data, branches, out, *more):
    from drivesim_reference import train

    train.main(["steering", "--weights", str(weights), "--episodes", str(data), "--branches", str(branches),
                "--out", str(out), "--steps", "6", "--batch", "3", "--fed", "2", "--triplets", "2", "--lr", "1e-2",
                "--device", "cpu", *more])


@pytest.fixture
def files(tmp_path):
    torch.manual_seed(1)
    weights = tmp_path / "w.safetensors"
    save_drivesim(DriveSim(HEAD_CFG, policy_width=3), HEAD_CFG, weights, "f32", actions=ACTIONS, frame_hz=12.5)
    return (weights, reward_episodes(tmp_path / "e.safetensors", lengths=(9, 12), rewards=False),
            branch_file(tmp_path / "b.safetensors"))


def test_train_steering_trains_the_transition_keeps_the_rest_and_resumes_to_the_same_bytes(tmp_path, files):
    weights, data, branches = files
    run(weights, data, branches, tmp_path / "whole.safetensors")
    before, after = load_file(str(weights)), load_file(str(tmp_path / "whole.safetensors"))
    assert sorted(after) == sorted(before)
    assert all(not torch.equal(after[k], before[k]) for k in TRANSITION), "every tensor of the step learnt"
    assert all(torch.equal(after[k], before[k]) for k in set(before) - set(TRANSITION))

    def again(w, d, out, *more):
        run(w, d, branches, out, *more)

    assert_resumes_to_the_same_bytes(again, weights, data, tmp_path, "--effect", "2")


def test_the_effect_term_learns_what_the_steering_did(tmp_path, files):
    """With the effect's weight the predicted difference between a point's +x and -x branches
    comes nearer the real one than in the same run without it."""
    from drivesim import episodes
    from drivesim_reference.model import load_drivesim
    from drivesim_reference.sequences import encode, predict

    weights, data, branches = files
    for weight in ("0", "30"):
        run(weights, data, branches, tmp_path / f"e{weight}.safetensors", "--effect", weight, "--steps", "40",
            "--branch-weight", "0")
    recorded = episodes.read(branches)
    errors = {}
    for weight in ("0", "30"):
        model, _ = load_drivesim(tmp_path / f"e{weight}.safetensors")
        with torch.no_grad():
            z = encode(model, torch.from_numpy(recorded.frames), 64).view(2, 3, 7, -1)
            c = torch.from_numpy(recorded.actions).view(2, 3, 7, 2)[:, :, :-1]
            predicted = predict(model.transition, z.flatten(0, 1), c.flatten(0, 1), 5).view(2, 3, 6, -1)
            errors[weight] = float(effect_error(predicted, z[:, :, 1:]))
    assert errors["30"] < 0.8 * errors["0"], errors


def test_the_effect_error_is_the_difference_of_the_outer_branches():
    real = torch.randn(2, 3, 4, 5)
    assert float(effect_error(real, real)) == 0.0
    shifted = real.clone()
    shifted[:, 2] += 0.5  # the +x branch predicted 0.5 too far in every code
    assert float(effect_error(shifted, real)) == pytest.approx(0.25)
    shifted[:, 1] += 9.0  # the straight branch is not part of the effect
    assert float(effect_error(shifted, real)) == pytest.approx(0.25)


@pytest.mark.parametrize("bad", ["metadata", "length", "settings"])
def test_a_file_not_of_branches_or_bad_settings_exit_with_a_message(tmp_path, files, bad):
    weights, data, branches = files
    more = []
    if bad == "metadata":
        branches = branch_file(tmp_path / "plain.safetensors", metadata=False)
    elif bad == "length":
        branches = reward_episodes(tmp_path / "b3.safetensors", lengths=(7, 7, 8), rewards=False)
    else:
        more = ["--effect", "-1"]
    with pytest.raises(SystemExit):
        run(weights, data, branches, tmp_path / "x.safetensors", *more)
    assert not (tmp_path / "x.safetensors").exists()

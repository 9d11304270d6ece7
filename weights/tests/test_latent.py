"""`train.py latent` (train_latent.py): the transition and its texture net trained together as a
conditional VAE. It trains the transition and adds the texture net and keeps every other tensor
(with --freeze-transition the transition's too), a run stopped after a checkpoint goes on to the
same bytes, and the KL term is the closed form's."""

import pytest
import torch
from safetensors.torch import load_file
from torch.distributions import Normal, kl_divergence

from drivesim_reference.model import DriveSim, save_drivesim
from drivesim_reference.train_latent import kl_from_standard
from test_heads import ACTIONS, HEAD_CFG, reward_episodes
from test_texture import assert_resumes_to_the_same_bytes

TRANSITION = [f"transition.{n}" for n in ("A", "U", "V", "W", "a", "b")]
TEXTURE = [f"transition.texture.{l}.{p}" for l in ("hidden", "output") for p in ("bias", "weight")]


def run(weights, data, out, *more):
    from drivesim_reference import train

    train.main(["latent", "--weights", str(weights), "--episodes", str(data), "--out", str(out), "--steps", "6",
                "--batch", "3", "--fed", "2", "--width", "4", "--posterior-width", "5", "--lr", "1e-2",
                "--device", "cpu", *more])


@pytest.fixture
def files(tmp_path):
    torch.manual_seed(1)
    weights = tmp_path / "w.safetensors"
    save_drivesim(DriveSim(HEAD_CFG, policy_width=3), HEAD_CFG, weights, "f32", actions=ACTIONS, frame_hz=12.5)
    return weights, reward_episodes(tmp_path / "e.safetensors", lengths=(9, 12), rewards=False)


def test_train_latent_trains_the_transition_adds_the_texture_net_and_resumes_to_the_same_bytes(tmp_path, files):
    weights, data = files
    run(weights, data, tmp_path / "whole.safetensors")
    before, after = load_file(str(weights)), load_file(str(tmp_path / "whole.safetensors"))
    assert sorted(set(after) - set(before)) == TEXTURE
    assert all(not torch.equal(after[k], before[k]) for k in TRANSITION), "every tensor of the step learnt"
    kept = set(before) - set(TRANSITION)
    assert all(torch.equal(after[k], before[k]) and after[k].dtype == before[k].dtype for k in kept)
    assert after["transition.texture.output.weight"].abs().max() > 0, "the net moved from the mean"
    assert_resumes_to_the_same_bytes(run, weights, data, tmp_path, "--beta", "2")


def test_freeze_transition_trains_the_texture_net_alone(tmp_path, files):
    weights, data = files
    run(weights, data, tmp_path / "frozen.safetensors", "--freeze-transition")
    before, after = load_file(str(weights)), load_file(str(tmp_path / "frozen.safetensors"))
    assert sorted(set(after) - set(before)) == TEXTURE
    assert all(torch.equal(after[k], v) for k, v in before.items())


@pytest.mark.parametrize("bad", [["--beta", "-1"], ["--lr", "0"], ["--fed", "0"], ["--width", "0"],
                                 ["--mean-weight", "-1"], ["--mean-weight", "nan"]])
def test_bad_settings_exit_with_a_message(tmp_path, files, bad):
    weights, data = files
    with pytest.raises(SystemExit):
        run(weights, data, tmp_path / "x.safetensors", *bad)
    assert not (tmp_path / "x.safetensors").exists()


def test_mean_weight_keeps_what_the_actions_do_in_the_mean(tmp_path, files):
    """--mean-weight M: the mean `A h' + a` learns the next code itself, so the mean world's
    fed-back error falls below that of the same run without it (where the posterior's noise may
    carry the difference); the sampled error is still trained."""
    from drivesim_reference.model import load_drivesim
    from drivesim_reference.sequences import encode, predict
    from drivesim import episodes

    weights, data = files
    for m in ("0", "30"):
        run(weights, data, tmp_path / f"m{m}.safetensors", "--mean-weight", m, "--steps", "40")
    recorded = episodes.read(data)
    errors = {}
    for m in ("0", "30"):
        model, _ = load_drivesim(tmp_path / f"m{m}.safetensors")
        with torch.no_grad():
            codes = encode(model, torch.from_numpy(recorded.frames), 64)
            z, c = codes[None, :9], torch.from_numpy(recorded.actions)[None, :8]
            errors[m] = float((predict(model.transition, z, c, 3) - z[:, 1:]).square().mean())
    assert errors["30"] < 0.8 * errors["0"], errors


def test_kl_is_the_closed_form():
    torch.manual_seed(3)
    mean, log_sd = torch.randn(4, 7), torch.randn(4, 7).clamp(-2, 2)
    expected = kl_divergence(Normal(mean, log_sd.exp()), Normal(0.0, 1.0)).sum(-1)
    assert torch.allclose(kl_from_standard(mean, log_sd), expected, atol=1e-5)
    assert torch.equal(kl_from_standard(torch.zeros(2, 3), torch.zeros(2, 3)), torch.zeros(2))

"""The transition's texture net (`transition.texture.*`, train_texture.py): `train.py texture`
adds it and keeps every other tensor, a run stopped after a checkpoint goes on to the same bytes,
and the sampled rollouts of sequences.py draw through it. (The crate reads it as PyTorch writes
it: tests/sampling.rs on fixtures.py's texture_f32.)"""

import pytest
import torch
from safetensors.torch import load_file

from drivesim_reference.model import DriveSim, save_drivesim
from drivesim_reference.sequences import predict
from test_heads import ACTIONS, HEAD_CFG, reward_episodes


def run(weights, data, out, *more):
    from drivesim_reference import train

    train.main(["texture", "--weights", str(weights), "--episodes", str(data), "--out", str(out), "--steps", "6",
                "--batch", "3", "--fed", "2", "--frames", "1", "--width", "4", "--device", "cpu", *more])


def test_train_texture_adds_the_net_keeps_the_rest_and_resumes_to_the_same_bytes(tmp_path):
    torch.manual_seed(1)
    weights = tmp_path / "w.safetensors"
    save_drivesim(DriveSim(HEAD_CFG, policy_width=3), HEAD_CFG, weights, "f16", actions=ACTIONS, frame_hz=12.5)
    data = reward_episodes(tmp_path / "e.safetensors", lengths=(9, 12), rewards=False)
    run(weights, data, tmp_path / "whole.safetensors")
    before, after = load_file(str(weights)), load_file(str(tmp_path / "whole.safetensors"))
    added = sorted(set(after) - set(before))
    assert added == [f"transition.texture.{l}.{p}" for l in ("hidden", "output") for p in ("bias", "weight")]
    assert all(torch.equal(after[k], v) and after[k].dtype == v.dtype for k, v in before.items())
    assert after["transition.texture.output.weight"].abs().max() > 0, "the net moved from the mean"
    assert_resumes_to_the_same_bytes(run, weights, data, tmp_path, "--width", "3")


def assert_resumes_to_the_same_bytes(run, weights, data, tmp_path, *other_run):
    """A run of 6 steps wrote `tmp_path/whole.safetensors`: one stopped after 4 (its checkpoint
    written) and run again writes its bytes, and a run with `other_run`'s arguments will not go
    on from that checkpoint."""
    ckpt = tmp_path / "run.ckpt"
    run(weights, data, tmp_path / "part.safetensors", "--checkpoint", str(ckpt), "--checkpoint-every", "2",
        "--steps", "4")
    run(weights, data, tmp_path / "resumed.safetensors", "--checkpoint", str(ckpt), "--checkpoint-every", "2")
    assert (tmp_path / "resumed.safetensors").read_bytes() == (tmp_path / "whole.safetensors").read_bytes()
    with pytest.raises(SystemExit):
        run(weights, data, tmp_path / "x.safetensors", "--checkpoint", str(ckpt), *other_run)


def test_sampled_rollouts_draw_through_the_texture_net():
    torch.manual_seed(2)
    model = DriveSim(HEAD_CFG, spread=True, texture_width=3)
    z, c = torch.randn(2, 6, HEAD_CFG.z_dim), torch.randn(2, 5, 2)
    mean = predict(model.transition, z, c, 2)
    with torch.no_grad():
        model.transition.texture.output.bias.fill_(0.5)  # a constant offset, whatever the noise
        model.transition.S.fill_(5.0)  # the spread head's noise would be huge: it is not drawn
    drawn = predict(model.transition, z, c, 2, temperature=1.0, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(drawn[:, 0], mean[:, 0] + 0.5)


def test_from_model_starts_from_the_files_own_net_and_the_pairs_critic_trains_and_resumes(tmp_path):
    torch.manual_seed(3)
    weights, plain = tmp_path / "w.safetensors", tmp_path / "plain.safetensors"
    model = DriveSim(HEAD_CFG, policy_width=3, texture_width=3)
    with torch.no_grad():
        model.transition.texture.output.weight.normal_()
    save_drivesim(model, HEAD_CFG, weights, "f32", actions=ACTIONS, frame_hz=12.5)
    save_drivesim(DriveSim(HEAD_CFG, policy_width=3), HEAD_CFG, plain, "f32", actions=ACTIONS, frame_hz=12.5)
    data = reward_episodes(tmp_path / "e.safetensors", lengths=(9, 12), rewards=False)
    run(weights, data, tmp_path / "same.safetensors", "--from-model", "--steps", "0")
    assert (tmp_path / "same.safetensors").read_bytes() == weights.read_bytes(), "0 steps: the file's own net"
    run(weights, data, tmp_path / "whole.safetensors", "--from-model", "--pairs", "1", "--width", "5")
    before, after = load_file(str(weights)), load_file(str(tmp_path / "whole.safetensors"))
    assert after["transition.texture.hidden.bias"].shape == (3,), "the file's width, not --width's"
    assert not torch.equal(after["transition.texture.output.weight"], before["transition.texture.output.weight"])
    from_model = ("--from-model", "--pairs", "1", "--width", "5")
    assert_resumes_to_the_same_bytes(lambda *a: run(*a, *from_model), weights, data, tmp_path, "--bestof", "2")
    with pytest.raises(SystemExit):
        run(plain, data, tmp_path / "x.safetensors", "--from-model")

"""Light checks of the reference model and the weight format: weights/tool -m pytest"""

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from drivesim_reference.export import export_onnx
from drivesim_reference.model import CONFIG_KEY, DTYPES, Config, DriveSim, load_drivesim, save_drivesim

CFG = Config(16, 32, 2, 3, z_dim=5, hidden_dim=7, action_dim=3)


@pytest.fixture
def model():
    torch.manual_seed(0)
    return DriveSim(CFG).eval()


def test_shapes(model):
    frames = torch.rand(4, CFG.channels, CFG.height, CFG.width) * 2 - 1
    mean, logsigma = model.encoder(frames)
    assert mean.shape == logsigma.shape == (4, CFG.z_dim)
    assert model.generator(mean).shape == frames.shape
    z, h = model.transition(mean, torch.zeros(4, CFG.hidden_dim), torch.zeros(4, CFG.action_dim))
    assert z.shape == (4, CFG.z_dim) and h.shape == (4, CFG.hidden_dim)
    assert model.rollout(frames[:3], torch.zeros(7, CFG.action_dim)).shape == (5, CFG.z_dim)


@pytest.mark.parametrize("dtype", ["f32", "f16", "bf16"])
def test_round_trip(model, tmp_path, dtype):
    path = tmp_path / "m.safetensors"
    save_drivesim(model, CFG, path, dtype)
    with safe_open(str(path), "pt") as f:
        assert json.loads(f.metadata()[CONFIG_KEY]) == json.loads(CFG.to_json())
        assert not any(k.endswith("num_batches_tracked") for k in f.keys())
    loaded, cfg = load_drivesim(path)
    assert cfg == CFG
    for k, v in loaded.state_dict().items():
        if not k.endswith("num_batches_tracked"):
            assert torch.equal(v, model.state_dict()[k].to(DTYPES[dtype]).float()), k


def test_a_failed_save_leaves_the_old_file_whole(model, tmp_path, monkeypatch):
    """A save that fails as the data is flushed (a full disk) leaves the old weights loadable,
    and no temporary file beside them."""
    from drivesim_reference import model as model_module

    path = tmp_path / "m.safetensors"
    save_drivesim(model, CFG, path)
    before = path.read_bytes()

    def full_disk(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(model_module._files.os, "fsync", full_disk)
    with pytest.raises(OSError, match=r"cannot write .*m.safetensors: No space left"):
        save_drivesim(DriveSim(CFG), CFG, path, "f16")
    monkeypatch.undo()
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == [path.name]
    load_drivesim(path)


def test_rejects_mixed_dtypes(model, tmp_path):
    path = tmp_path / "m.safetensors"
    save_drivesim(model, CFG, path)
    tensors = load_file(str(path))
    tensors["transition.a"] = tensors["transition.a"].half()
    save_file(tensors, str(path), metadata={CONFIG_KEY: CFG.to_json()})
    with pytest.raises(ValueError, match="one of"):
        load_drivesim(path)


def test_config_requires_all_keys():
    d = json.loads(CFG.to_json())
    del d["kernel"]
    with pytest.raises(ValueError):
        Config.from_json(json.dumps(d))


def test_onnx_matches_torch(model, tmp_path):
    export_onnx(model, CFG, tmp_path)
    assert not any(m.training for m in model.modules()), "export must leave the model in eval mode"
    frame = torch.rand(1, CFG.channels, CFG.height, CFG.width) * 2 - 1
    z, h, c = torch.randn(1, CFG.z_dim), torch.randn(1, CFG.hidden_dim), torch.randn(1, CFG.action_dim)
    with torch.no_grad():
        expected = {
            "encoder": [model.encoder(frame)[0]],
            "generator": [model.generator(z)],
            "transition": list(model.transition(z, h, c)),
        }
    inputs = {"encoder": {"frame": frame}, "generator": {"z": z}, "transition": {"z": z, "h": h, "c": c}}
    for name, feeds in inputs.items():
        sess = ort.InferenceSession(str(tmp_path / f"{name}.onnx"))
        got = sess.run(None, {k: v.numpy() for k, v in feeds.items()})
        for g, e in zip(got, expected[name]):
            np.testing.assert_allclose(g, e.numpy(), rtol=1e-5, atol=1e-5)


def test_the_optional_networks_load_and_round_trip(tmp_path):
    """The spread head (`transition.S`, `.s`) and the policy (`policy.*`) are part of a file
    where it has them, and absent where it has not: the default weights (with both) loaded,
    which failed before."""
    torch.manual_seed(3)
    full = DriveSim(CFG, spread=True, policy_width=4).eval()
    with torch.no_grad():
        full.transition.S.normal_()
    path = tmp_path / "full.safetensors"
    save_drivesim(full, CFG, path)
    loaded, _ = load_drivesim(path)
    assert loaded.transition.spread and loaded.policy.hidden.out_features == 4
    for (name, a), (_, b) in zip(full.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), name
    h = torch.randn(2, CFG.hidden_dim)
    assert torch.equal(loaded.transition.log_sigma(h), h @ full.transition.S.T + full.transition.s)
    default, _ = load_drivesim(Path(__file__).resolve().parents[1] / "default.safetensors")
    assert default.transition.spread and default.policy.hidden.out_features == 64
    path = tmp_path / "plain.safetensors"
    save_drivesim(DriveSim(CFG).eval(), CFG, path)
    plain, _ = load_drivesim(path)
    assert not plain.transition.spread and not hasattr(plain, "policy")


def test_a_sharpened_noise_factor_keeps_unit_spreads_and_gathers_the_correlation():
    """sequences.sharpen_noise: power 1 gives the factor back; power 2 is the Cholesky factor of
    the correlation squared, back to unit diagonal: fewer directions carry the noise."""
    from drivesim_reference.sequences import sharpen_noise

    torch.manual_seed(5)
    mix = torch.randn(40, 6) @ torch.randn(6, 6)
    corr = torch.corrcoef(mix.T).double()
    factor = torch.linalg.cholesky(corr).float()
    assert torch.equal(sharpen_noise(factor, 1), factor)
    sharp = sharpen_noise(factor, 2)
    c = (sharp @ sharp.T).double()
    assert torch.allclose(sharp, sharp.tril()) and torch.allclose(c.diagonal(), torch.ones(6, dtype=torch.float64), atol=1e-5)
    squared = corr @ corr
    d = squared.diagonal().sqrt()
    assert torch.allclose(c, squared / torch.outer(d, d), atol=1e-5)

    def participation(m):
        w = torch.linalg.eigvalsh(m)
        return float(w.sum() ** 2 / (w**2).sum())

    assert participation(c) < participation(corr)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="power"):
            sharpen_noise(factor, bad)
    with pytest.raises(ValueError, match="square"):
        sharpen_noise(factor[:5], 2)


def test_the_noise_factor_round_trips_and_correlates_the_samples(tmp_path):
    """`transition.L` (sequences.noise_factor) is saved and loaded with the spread head, and a
    sampled prediction draws `L @ eps`: with L's rows swapped, the same draws land swapped."""
    from drivesim_reference.sequences import noise_factor, predict

    torch.manual_seed(4)
    model = DriveSim(CFG, spread=True).eval()
    with torch.no_grad():
        model.transition.S.normal_(std=0.1)
    drives = [(torch.randn(12, CFG.z_dim), torch.randn(11, CFG.action_dim)) for _ in range(3)]
    factor = noise_factor(model.transition, drives)
    assert torch.allclose(factor, factor.tril()) and (factor.diagonal() > 0).all()
    assert torch.allclose((factor @ factor.T).diagonal(), torch.ones(CFG.z_dim), atol=1e-5)
    model.transition.set_noise_factor(factor)
    path = tmp_path / "correlated.safetensors"
    save_drivesim(model, CFG, path)
    loaded, _ = load_drivesim(path)
    assert loaded.transition.correlated and torch.equal(loaded.transition.L, factor)
    z, c = torch.randn(2, 4, CFG.z_dim), torch.randn(2, 3, CFG.action_dim)

    def sample(factor):
        loaded.transition.set_noise_factor(factor)
        return predict(loaded.transition, z, c, 1, temperature=1.0, generator=torch.Generator().manual_seed(7))

    mean = predict(loaded.transition, z, c, 4)  # teacher-forced throughout: the means of every step
    swap = torch.eye(CFG.z_dim)[[1, 0, 2, 3, 4]]
    first, swapped = sample(torch.eye(CFG.z_dim))[:, 0], sample(swap)[:, 0]
    _, hidden = predict(loaded.transition, z, c, 4, hidden=True)
    sigma = loaded.transition.log_sigma(hidden[:, 0]).clamp(-20, 20).exp()
    eps = (first - mean[:, 0]) / sigma
    assert torch.allclose((swapped - mean[:, 0]) / sigma, eps @ swap.T, atol=1e-5)
    assert not torch.allclose(eps @ swap.T, eps)
    with pytest.raises(ValueError, match="spread head"):
        DriveSim(CFG).transition.set_noise_factor(factor)


def test_export_from_a_drivesim_file_keeps_its_frame_rate_and_takes_new_actions(tmp_path):
    """`export M.safetensors --out N --actions A.json`: the tensors and the frame rate as they
    were (a file re-exported lost `drivesim.frame_hz`), the actions given."""
    from drivesim_reference.export import main

    torch.manual_seed(0)
    actions = [dict(name=f"a{i}", unit="u", mean=0.0, std=1.0, min=-1.0, max=1.0) for i in range(CFG.action_dim)]
    save_drivesim(DriveSim(CFG), CFG, tmp_path / "in.safetensors", "f32", actions=actions, frame_hz=12.5)
    narrower = [dict(a, max=0.5) for a in actions]
    (tmp_path / "actions.json").write_text(json.dumps(narrower))
    assert main([str(tmp_path / "in.safetensors"), "--out", str(tmp_path / "out.safetensors"),
                 "--actions", str(tmp_path / "actions.json")]) == 0
    with safe_open(str(tmp_path / "out.safetensors"), "pt") as f:
        meta = f.metadata()
    assert meta["drivesim.frame_hz"] == "12.5" and json.loads(meta["drivesim.actions"]) == narrower
    before, after = load_file(tmp_path / "in.safetensors"), load_file(tmp_path / "out.safetensors")
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)

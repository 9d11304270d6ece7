"""The PyTorch side's data measures: the evaluation's road offset, a tiny fit and eval, the
actions' normalisation folded into the weights."""

import json

import numpy as np
import pytest

from drivesim import episodes


def test_road_offset_finds_a_grey_band():
    pytest.importorskip("torch")
    from drivesim_reference import evaluation

    frame = np.zeros((80, 160, 3), np.uint8)
    frame[..., 1] = 200  # grass
    assert evaluation.road_offset(frame) is None
    frame[:, 100:120] = 105  # road from column 100 to 119: its centre 29.5 px right of the car
    assert evaluation.road_offset(frame) == pytest.approx(29.5)
    grass = np.zeros_like(frame)
    grass[..., 1] = 200
    left = grass.copy()
    left[:, 40:60] = 105  # centre 49.5: 30.5 px left of the car
    # Frames without road do not count; the others' offsets are averaged.
    assert evaluation.mean_offset([frame, grass, left]) == pytest.approx((29.5 - 30.5) / 2)
    assert evaluation.mean_offset([grass]) is None


def test_fit_and_eval_tiny(tmp_path):
    """A few steps of both training phases and the evaluation, on a tiny model and data set."""
    torch = pytest.importorskip("torch")
    from drivesim_reference import sequences
    from drivesim_reference import train
    from drivesim_reference.model import load_drivesim

    rng = np.random.default_rng(1)
    data = episodes.Episodes(
        rng.integers(0, 256, (240, 32, 64, 3), dtype=np.uint8),
        np.stack([rng.uniform(10, 40, 240), rng.uniform(-1, 1, 240)], 1).astype(np.float32),
        np.array([0, 120], dtype=np.int64),
    )
    episodes.write(tmp_path / "d.safetensors", data, {"frame_hz": "12.5"})
    assert episodes.metadata(tmp_path / "d.safetensors") == {"frame_hz": "12.5"}
    (tmp_path / "text.safetensors").write_text("# not a safetensors file\n")
    with pytest.raises(episodes.EpisodesError, match="not a .gzipped. safetensors file"):
        episodes.metadata(tmp_path / "text.safetensors")
    train.main(["fit", "--data", str(tmp_path / "d.safetensors"), "--out", str(tmp_path / "m.safetensors"),
                "--device", "cpu", "--base-channels", "4", "--z-dim", "8", "--hidden-dim", "8",
                "--vae-steps", "2", "--transition-steps", "2", "--batch", "4", "--transition-batch", "4"])
    model, cfg = load_drivesim(tmp_path / "m.safetensors")
    assert (cfg.height, cfg.width, cfg.z_dim) == (32, 64, 8)
    from safetensors import safe_open
    with safe_open(str(tmp_path / "m.safetensors"), framework="pt") as f:
        assert f.metadata()["drivesim.frame_hz"] == "12.5"  # the data's rate travels with the weights
    train.main(["eval", "--weights", str(tmp_path / "m.safetensors"), "--data", str(tmp_path / "d.safetensors"),
                "--figures", str(tmp_path / "fig"), "--seed-clip", str(tmp_path / "clip.safetensors"),
                "--reference", str(tmp_path / "d.safetensors")])
    for name in ("eval.json", "reconstruction.png", "steering.png", "contact_sheet.png"):
        assert (tmp_path / "fig" / name).is_file()
    result = json.loads((tmp_path / "fig" / "eval.json").read_text())
    fidelity = result["fidelity"]
    assert result["futures"]["at_30_steps"]["real_futures"]["reference_windows"] > 0
    assert fidelity["psnr_p10_db"] <= fidelity["psnr_db"]
    latent = fidelity["latent"]
    assert latent["windows"] > 0 and latent["ratio_30"] > 0
    # Step by step, apart from sequences.predict: the error after k fed-back steps, and over the first k.
    codes = sequences.encode(model, torch.from_numpy(data.frames), 256)
    acts = torch.from_numpy(data.actions)
    per_step = []
    with torch.no_grad():
        for s in data.windows(sequences.TEACHER + 30)[::5]:
            h, errs = torch.zeros(1, cfg.hidden_dim), []
            for t in range(sequences.TEACHER + 29):
                if t < sequences.TEACHER:
                    z = codes[s + t][None]
                z, h = model.transition(z, h, acts[s + t][None])
                if t >= sequences.TEACHER - 1:
                    errs.append(float((z[0] - codes[s + t + 1]).square().mean()))
            per_step.append(errs)
    per_step = np.mean(per_step, axis=0)  # [30]: the error after 1..30 fed-back steps
    for k in (10, 30):
        assert latent[f"mse_{k}"] == pytest.approx(per_step[k - 1], rel=1e-4)
        assert latent[f"mse_1_to_{k}"] == pytest.approx(per_step[:k].mean(), rel=1e-4)
    assert set(fidelity["road_moves_right_way"]) == {"0.3", "0.6"}
    futures = json.loads((tmp_path / "fig" / "eval.json").read_text())["futures"]
    assert set(futures["steering_probe"]) == {"1", "2", "3", "5", "10", "30"} and set(futures["steering_probe"]["30"]) == {"0.3", "0.6"}
    assert futures["at_30_steps"]["windows"] > 0 and "sampled" not in futures["at_30_steps"]
    assert set(futures["texture"]) == {"steps", "windows", "recorded", "reconstruction", "mean", "linear", "copy"}
    assert episodes.read(tmp_path / "clip.safetensors").frames.shape == (8, 32, 64, 3)


def test_action_normalisation_is_folded_into_u_and_b():
    """After training, the transition on raw actions equals the trained one on normalised actions."""
    torch = pytest.importorskip("torch")
    import argparse
    from drivesim_reference import sequences
    from drivesim_reference.checkpoints import Checkpoints
    from drivesim_reference.model import Config, DriveSim

    torch.manual_seed(0)
    cfg = Config(height=16, width=16, channels=3, base_channels=2, z_dim=4, hidden_dim=6)
    model = DriveSim(cfg)
    codes = torch.randn(40, 4)
    actions = torch.stack([torch.rand(40) * 30 + 5, torch.rand(40) * 2 - 1], 1)
    args = argparse.Namespace(transition_lr=1e-3, transition_steps=1, transition_batch=4, seed=0, log_every=1)
    args = argparse.Namespace(**vars(args), checkpoint=None, checkpoint_every=1, resume=False)
    starts = np.arange(0, 40 - sequences.SEQ + 1)
    norm = sequences.train_transition(model, None, codes, actions, starts, args, [], Checkpoints(args, "cpu"))
    mean, std = torch.tensor(norm["action_mean"]), torch.tensor(norm["action_std"])
    tr = model.transition
    z, h, c = torch.randn(3, 4), torch.randn(3, 6), actions[:3]
    with torch.no_grad():
        folded = tr(z, h, c)
        u, b = tr.U * std, tr.b + (tr.U * std) @ (mean / std)  # undo the fold
        h_ref = torch.tanh(h @ tr.W.T + z @ tr.V.T + ((c - mean) / std) @ u.T + b)
    torch.testing.assert_close(folded[1], h_ref)

"""Tests of the data tools: episodes format, comma converter, CarRacing recorder."""

import json
import re

import h5py
import numpy as np
import pytest

import convert_comma
import episodes


def make_episodes(n=6, starts=(0, 4)):
    rng = np.random.default_rng(0)
    return episodes.Episodes(
        rng.integers(0, 256, (n, 8, 16, 3), dtype=np.uint8),
        rng.standard_normal((n, 2)).astype(np.float32),
        np.array(starts, dtype=np.int64),
    )


@pytest.mark.parametrize("name", ["e.safetensors", "e.safetensors.gz"])
def test_episodes_round_trip(tmp_path, name):
    e = make_episodes()
    episodes.write(tmp_path / name, e, {"note": "x"})
    back = episodes.read(tmp_path / name)
    for k in ("frames", "actions", "episode_starts"):
        np.testing.assert_array_equal(getattr(back, k), getattr(e, k))
    assert back.bounds() == [(0, 4), (4, 6)]


@pytest.mark.parametrize("change, message", [
    (dict(starts=(1, 4)), "begin at 0"),
    (dict(starts=(0, 4, 4)), "strictly increasing"),
    (dict(starts=(0, 6)), "past the last frame"),
])
def test_episodes_reject_bad_starts(change, message):
    with pytest.raises(episodes.EpisodesError, match=message):
        make_episodes(**change)


def test_episodes_reject_bad_arrays():
    e = make_episodes()
    with pytest.raises(episodes.EpisodesError, match="uint8"):
        episodes.Episodes(e.frames.astype(np.float32), e.actions, e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match=r"\[6,2\]"):
        episodes.Episodes(e.frames, e.actions[:5], e.episode_starts)


def test_episodes_from_lists():
    # Lists are converted to the format's dtypes when no value changes, and rejected otherwise.
    e = make_episodes()
    back = episodes.Episodes(e.frames.tolist(), e.actions.tolist(), [0, 4])
    for k in ("frames", "actions", "episode_starts"):
        np.testing.assert_array_equal(getattr(back, k), getattr(e, k))
        assert getattr(back, k).dtype == getattr(e, k).dtype
    with pytest.raises(episodes.EpisodesError, match="frames: values do not fit uint8"):
        episodes.Episodes((e.frames.astype(np.int64) + 256).tolist(), e.actions, e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match="episode_starts: values do not fit int64"):
        episodes.Episodes(e.frames, e.actions, [0, 4.5])
    with pytest.raises(episodes.EpisodesError, match="actions: not a regular array"):
        episodes.Episodes(e.frames, [[1.0, 2.0], [3.0]], e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match="actions must be numbers"):
        episodes.Episodes(e.frames, [["a", "b"]] * 6, e.episode_starts)


def test_episodes_read_errors(tmp_path):
    with pytest.raises(episodes.EpisodesError, match="no such file"):
        episodes.read(tmp_path / "missing.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(episodes.EpisodesError, match="not a"):
        episodes.read(tmp_path / "junk.safetensors")


def write_drive(root, rows_per_frame, n_frames=10):
    """A synthetic camera/log pair. Frame f is filled with the value 10*f; every log row of
    frame f has speed f and steering 2*f, except one glitch row with steering 999."""
    (root / "camera").mkdir(parents=True, exist_ok=True)
    (root / "log").mkdir(parents=True, exist_ok=True)
    x = np.repeat(np.arange(n_frames, dtype=np.uint8) * 10, 3 * 160 * 320).reshape(n_frames, 3, 160, 320)
    ptr = np.concatenate([np.full(k, f, dtype=np.float64) for f, k in enumerate(rows_per_frame)])
    speed, steer = ptr.copy(), 2 * ptr
    steer[1] = 999.0  # glitch row in frame 0, dropped
    with h5py.File(root / "camera" / "d.h5", "w") as f:
        f["X"] = x
    with h5py.File(root / "log" / "d.h5", "w") as f:
        f["cam1_ptr"], f["speed"], f["steering_angle"] = ptr, speed, steer
    return root / "camera" / "d.h5"


def set_log(root, name, values):
    with h5py.File(root / "log" / "d.h5", "a") as f:
        del f[name]
        f[name] = values


def test_comma_aligns_through_cam1_ptr(tmp_path):
    # 4-6 rows per frame, and rows for frames 10 and 11 that do not exist.
    cam = write_drive(tmp_path, [5, 4, 6, 5, 5, 4, 6, 5, 5, 4, 5, 5])
    e = convert_comma.convert_drive(cam, min_frames=1)
    assert e.frames.shape == (10, 80, 160, 3)
    np.testing.assert_array_equal(e.frames[:, 0, 0, 0], np.arange(10) * 10)
    np.testing.assert_allclose(e.actions[:, 0], np.arange(10))
    np.testing.assert_allclose(e.actions[:, 1], 2 * np.arange(10))
    assert list(e.episode_starts) == [0]


def test_comma_splits_at_frames_without_rows(tmp_path):
    # Frame 4 has no log rows: two episodes, 0-3 and 5-9.
    cam = write_drive(tmp_path, [5, 5, 5, 5, 0, 5, 5, 5, 5, 5])
    e = convert_comma.convert_drive(cam, min_frames=1)
    assert list(e.episode_starts) == [0, 4]
    np.testing.assert_array_equal(e.frames[:, 0, 0, 0], [0, 10, 20, 30, 50, 60, 70, 80, 90])
    # A stride keeps every other frame of each episode; min_frames drops short ones.
    e = convert_comma.convert_drive(cam, stride=2, min_frames=3)
    np.testing.assert_allclose(e.actions[:, 0], [5, 7, 9])


def test_comma_accepts_column_logs(tmp_path):
    # Log datasets stored as [R,1] convert exactly as [R] ones.
    flat = convert_comma.convert_drive(write_drive(tmp_path / "a", [5] * 10), min_frames=1)
    cam = write_drive(tmp_path / "b", [5] * 10)
    for name in ("cam1_ptr", "speed", "steering_angle"):
        with h5py.File(tmp_path / "b" / "log" / "d.h5", "r") as f:
            column = f[name][:][:, None]
        set_log(tmp_path / "b", name, column)
    e = convert_comma.convert_drive(cam, min_frames=1)
    np.testing.assert_array_equal(e.frames, flat.frames)
    np.testing.assert_array_equal(e.actions, flat.actions)


@pytest.mark.parametrize("name, shape", [
    ("cam1_ptr", (50, 2)), ("speed", (25, 2)), ("steering_angle", (50, 1, 1)), ("speed", ()),
])
def test_comma_rejects_bad_log_shapes(tmp_path, name, shape):
    cam = write_drive(tmp_path, [5] * 10)
    set_log(tmp_path, name, np.zeros(shape))
    message = f"log/d.h5: {name} must be [R] or [R,1], got {shape}"
    with pytest.raises(ValueError, match=re.escape(message)):
        convert_comma.convert_drive(cam, min_frames=1)


def test_comma_main_checks_every_input_first(tmp_path, capsys):
    # A bad log in the second drive stops the run before the first drive is converted,
    # with one line on stderr and exit status 2.
    good = write_drive(tmp_path / "a", [5] * 10)
    bad = write_drive(tmp_path / "b", [5] * 10)
    set_log(tmp_path / "b", "cam1_ptr", np.zeros((50, 2)))
    with pytest.raises(SystemExit) as exit_:
        convert_comma.main([str(good), str(bad), "--min-frames", "1", "--out", str(tmp_path / "e.safetensors")])
    assert exit_.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith("convert_comma: error: ") and "cam1_ptr" in err and err.count("\n") == 1


def test_comma_main_out_folder(tmp_path, capsys):
    cam = write_drive(tmp_path, [5] * 10)
    with pytest.raises(SystemExit) as exit_:
        convert_comma.main([str(cam), "--min-frames", "1", "--out", str(tmp_path / "missing" / "e.safetensors")])
    assert exit_.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""  # nothing was converted
    assert err == f"convert_comma: error: --out {tmp_path / 'missing' / 'e.safetensors'}: " \
                  f"folder {tmp_path / 'missing'} does not exist\n"
    convert_comma.main([str(cam), "--min-frames", "1", "--out", str(tmp_path / "e.safetensors")])
    assert len(episodes.read(tmp_path / "e.safetensors").frames) == 10


def test_comma_downsample_averages_blocks():
    x = np.zeros((1, 3, 160, 320), dtype=np.uint8)
    x[0, 0, 0, 0] = 200  # one bright pixel of a 2x2 block -> a quarter of it
    x[0, 2] = 7
    y = convert_comma.downsample(x)
    assert y.shape == (1, 80, 160, 3)
    assert (y[0, 0, 0] == [50, 0, 7]).all()


def test_comma_errors(tmp_path):
    with pytest.raises(ValueError, match="'camera' folder"):
        convert_comma.convert_drive(tmp_path / "d.h5")
    cam = write_drive(tmp_path, [5] * 10)
    (tmp_path / "log" / "d.h5").unlink()
    with pytest.raises(FileNotFoundError, match="log/d.h5"):
        convert_comma.convert_drive(cam)
    with h5py.File(tmp_path / "log" / "d.h5", "w") as f:
        f["speed"] = np.zeros(3)
    with pytest.raises(ValueError, match="missing datasets"):
        convert_comma.convert_drive(cam)
    write_drive(tmp_path, [5] * 10)
    set_log(tmp_path, "speed", np.zeros(40))
    with pytest.raises(ValueError, match="log/d.h5: log datasets differ in length"):
        convert_comma.convert_drive(cam)


def test_record_short_episode():
    record = pytest.importorskip("record")
    frames, actions, on_road, _, _ = record.record_episode(seed=3, frames=5, frame_skip=2)
    assert frames.shape == (5, 80, 160, 3) and frames.dtype == np.uint8
    assert actions.shape == (5, 2) and np.all(np.abs(actions[:, 1]) <= 1)
    assert 0 <= on_road <= 1
    assert record.parse_seeds("0-2,7") == [0, 1, 2, 7]


@pytest.mark.parametrize("style", ["varied", "varied-noise", "varied-holds", "holds", "hard", "jerky"])
def test_record_driver_styles(style):
    record = pytest.importorskip("record")
    frames, actions, _, _, _ = record.record_episode(seed=4, frames=40, frame_skip=2, style=style, random_colours=True)
    assert frames.shape == (40, 80, 160, 3) and np.all(np.abs(actions[:, 1]) <= 1)
    steady, _, _, _, _ = record.record_episode(seed=4, frames=1, frame_skip=2)
    # Random colours: the first frame (the car still at the start line) differs from the env's colours.
    assert np.abs(frames[0].astype(int) - steady[0]).mean() > 10


def test_jerky_driver_holds_its_steering_between_looks():
    record = pytest.importorskip("record")
    _, actions, _, _, _ = record.record_episode(seed=5, frames=60, frame_skip=2, style="jerky")
    steering = actions[:, 1]
    held = steering[1:] == steering[:-1]
    # Looks every 0.12-0.3 s, frames 0.04 s apart: each steering value lasts 3 to 8 frames.
    assert 0.6 < held.mean() < 0.9
    changes = np.flatnonzero(~held)
    assert np.all(np.diff(changes) >= 3) and np.all(np.diff(changes) <= 8)


def test_varied_noise_driver_redraws_its_noise_level():
    record = pytest.importorskip("record")
    from gymnasium.envs.box2d import car_racing

    env = car_racing.CarRacing()
    env.reset(seed=6)
    driver = record.Driver(env.track, np.random.default_rng(6), "varied-noise")
    env.close()
    levels = set()
    for _ in range(200):  # 200 frames of 0.08 s: manoeuvres last 1-4 s
        driver.lateral(0.08)
        levels.add(driver.steer_noise.sigma)
    assert len(levels) >= 4 and all(0.02 <= s <= 0.15 for s in levels)


def runs_of(values):
    """(length, value) of each run of equal consecutive values."""
    ends = [*np.flatnonzero(values[1:] != values[:-1]) + 1, len(values)]
    return [(end - start, values[start]) for start, end in zip([0, *ends[:-1]], ends)]


def test_varied_holds_driver_holds_constant_steering_open_loop():
    record = pytest.importorskip("record")
    # A hold: 0.2-0.8 s of one steering of 0.1-0.7, whatever the road: 3 to 10 frames of 0.08 s
    # (11 when the seconds left round just above zero).
    def holds(style):
        _, actions, _, _, _ = record.record_episode(seed=7, frames=400, frame_skip=4, style=style)
        return [n for n, s in runs_of(actions[:, 1]) if n >= 3 and 0.1 <= abs(s) <= 0.7]

    held = holds("varied-holds")
    assert len(held) >= 3 and max(held) <= 11
    assert holds("varied") == []  # pure pursuit with coloured noise never repeats a steering
    # `holds`: a hold, then a recovery of 0.4-1.2 s and back to the road, again and again.
    many = holds("holds")
    assert len(many) >= 8 and max(many) <= 11 and 0.1 < sum(many) / 400 < 0.5


def test_road_offset_finds_a_grey_band():
    pytest.importorskip("torch")
    import evaluation

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
    import sequences
    import train
    from model import load_drivesim

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
    assert set(futures["steering_probe"]) == {"5", "10", "30"} and set(futures["steering_probe"]["30"]) == {"0.3", "0.6"}
    assert futures["at_30_steps"]["windows"] > 0 and "sampled" not in futures["at_30_steps"]
    assert set(futures["texture"]) == {"steps", "windows", "recorded", "reconstruction", "mean", "linear", "copy"}
    assert episodes.read(tmp_path / "clip.safetensors").frames.shape == (8, 32, 64, 3)


def test_action_normalisation_is_folded_into_u_and_b():
    """After training, the transition on raw actions equals the trained one on normalised actions."""
    torch = pytest.importorskip("torch")
    import argparse
    import sequences
    from checkpoints import Checkpoints
    from model import Config, DriveSim

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


def test_a_failed_write_leaves_the_old_file_whole(tmp_path, monkeypatch):
    """A write that fails (here: the disk full when the data is flushed) leaves the file that was
    there as it was, and no temporary file beside it."""
    path = tmp_path / "data.safetensors.gz"
    old = make_episodes()
    episodes.write(path, old)

    def full_disk(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(episodes._files.os, "fsync", full_disk)
    with pytest.raises(OSError, match=r"cannot write .*data.safetensors.gz: No space left"):
        episodes.write(path, make_episodes(n=9, starts=(0, 3, 5)))
    monkeypatch.undo()
    back = episodes.read(path)
    np.testing.assert_array_equal(back.frames, old.frames)
    np.testing.assert_array_equal(back.episode_starts, old.episode_starts)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_written_files_are_the_same_bytes_for_the_same_data(tmp_path):
    """safetensors writes its metadata in a hash map's order and gzip a time stamp: a file written
    twice differed. Sorted and without the stamp, the same episodes are the same bytes."""
    metadata = {f"key{i}": f"value {i}" for i in range(8)}
    for name in ("a.safetensors", "b.safetensors", "a.safetensors.gz", "b.safetensors.gz"):
        episodes.write(tmp_path / name, make_episodes(), metadata)
    assert (tmp_path / "a.safetensors").read_bytes() == (tmp_path / "b.safetensors").read_bytes()
    assert (tmp_path / "a.safetensors.gz").read_bytes() == (tmp_path / "b.safetensors.gz").read_bytes()
    blob = (tmp_path / "a.safetensors").read_bytes()
    header = json.loads(blob[8:8 + int.from_bytes(blob[:8], "little")])
    assert list(header["__metadata__"]) == sorted(metadata)
    assert episodes.metadata(tmp_path / "a.safetensors.gz") == metadata


def test_mirror_images_flip_the_frames_and_negate_the_steering():
    data = make_episodes()
    both = data.with_mirror_images()
    n = len(data.frames)
    assert both.bounds() == data.bounds() + [(s + n, e + n) for s, e in data.bounds()]
    assert np.array_equal(both.frames[:n], data.frames)
    assert np.array_equal(both.frames[n:, :, 0], data.frames[:, :, -1])  # the left column was the right
    assert np.array_equal(both.actions[n:, 0], data.actions[:, 0])
    assert np.array_equal(both.actions[n:, 1], -data.actions[:, 1])
    assert np.array_equal(both.with_mirror_images().frames[3 * n:], data.frames)  # twice: the original

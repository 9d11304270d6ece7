"""Tests of the dream's measures against held-out episodes (futures.py, issue 31)."""

from types import SimpleNamespace

import numpy as np
import pytest

from drivesim import episodes

torch = pytest.importorskip("torch")


def test_frechet_distance_of_gaussians():
    from drivesim_reference.futures import frechet

    g = torch.Generator().manual_seed(0)
    a = torch.randn(4000, 3, generator=g, dtype=torch.float64)
    a -= a.mean(0)
    assert frechet(a, a) == pytest.approx(0.0, abs=1e-6)
    # Shifted by d: |d|^2. Scaled by 2: tr(ca) + tr(4 ca) - 2 tr(2 ca) = tr(ca).
    assert frechet(a + torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64), a) == pytest.approx(5.0, rel=1e-6)
    assert frechet(2 * a, a) == pytest.approx(float(torch.cov(a.T).trace()), rel=1e-6)


def test_real_futures_find_the_window_itself_in_a_reference_that_holds_it():
    from drivesim_reference.futures import FUTURES, real_futures

    g = torch.Generator().manual_seed(0)
    ref_z, ref_c = torch.randn(200, 35, 6, generator=g), torch.randn(200, 34, 2, generator=g)
    ref_codes = ref_z.flatten(0, 1)
    held_z, held_c = ref_z[:20].clone(), ref_c[:20].clone()
    base = float((ref_codes.mean(0) - held_z[:, -1]).square().mean())
    out = real_futures(held_z, held_c, base, ref_codes, ref_z, ref_c)
    # Each held-out window is its own nearest reference window: one of the 16 is its real future.
    assert out["nearest_windows"]["best_of_16_mse_ratio"] == pytest.approx(0.0, abs=1e-6)
    assert out["nearest_windows"]["one_mse_ratio"] == pytest.approx(0.0, abs=1e-6)
    # Independent random codes: one is about twice the mean code's error, the best of 16 well below one.
    random = out["random_codes"]
    assert 1.5 < random["one_mse_ratio"] < 2.5 and random["best_of_16_mse_ratio"] < 0.9 * random["one_mse_ratio"]
    assert out["reference_windows"] == 200 and FUTURES == 16
    assert real_futures(held_z, held_c, base, ref_codes, ref_z[:15], ref_c[:15]) is None  # fewer than 16


class FrameStepper(torch.nn.Module):
    """A transition whose codes are frame indices: each step moves `frames` frames on."""

    def __init__(self, frames):
        super().__init__()
        self.W, self.frames, self.spread, self.samples = torch.zeros(1, 1), frames, False, False

    def forward(self, z, h, c):
        return z + self.frames, h


class Dream:
    """What `road_tracking` and `texture` read of a model: its transition."""

    def __init__(self, frames):
        self.transition = FrameStepper(frames)


def test_road_tracking_compares_each_road_move_with_the_recorded_one():
    from drivesim_reference.futures import road_tracking

    n = 30
    frames = np.zeros((n, 80, 160, 3), np.uint8)
    frames[..., 1] = 200  # grass
    for t in range(n):
        frames[t, :, 40 + 2 * t:60 + 2 * t] = 105  # a road moving 2 px right per frame
    data = episodes.Episodes(frames, np.zeros((n, 2), np.float32), np.array([0]))
    codes = torch.arange(n, dtype=torch.float32)[:, None]
    actions = torch.zeros(n, 2)
    decode = lambda z: frames[z[:, 0].round().long().clamp(0, n - 1).numpy()]  # noqa: E731

    def track(frames_per_step, recon):
        return road_tracking(Dream(frames_per_step), data, codes, actions, decode, recon)

    faithful = track(1.0, frames)
    assert faithful["windows"] == len(data.windows(10)[::2]) > 0
    assert faithful["real_move_px"] == pytest.approx(10.0)  # 5 frames of 2 px
    assert faithful["reconstruction_slope"] == pytest.approx(1.0) and faithful["dream_slope"] == pytest.approx(1.0)
    assert track(0.6, frames)["dream_slope"] == pytest.approx(0.6)  # 3 frames on in 5 steps
    assert track(0.0, frames)["dream_slope"] == pytest.approx(0.0)  # a still road
    grass = np.broadcast_to(frames[0, 0, 0], frames.shape)  # every pixel the grass's
    assert track(1.0, grass)["windows"] == 0  # no reconstruction shows road


def carracing_frames(n):
    """n frames of CarRacing's colours: grass, a road, and from frame 5 on a patch of the lighter
    grass 30 pixels wide, one row taller each frame, and a kerb of 32 red pixels."""
    frames = np.zeros((n, 80, 160, 3), np.uint8)
    frames[:] = (102, 204, 102)
    frames[:, :, 70:90] = (102, 102, 102)
    for t in range(5, n):
        frames[t, :t - 4, :30] = (102, 230, 102)
        frames[t, 20:36, 90:92] = (255, 0, 0)
    return frames


def test_texture_figures_count_patch_and_kerb_pixels():
    from drivesim_reference.futures import texture_figures

    frames = carracing_frames(12)
    grass = 60 * 140 - 32  # the top 60 rows but the road and the kerb
    figures = texture_figures(frames[[0, 11]])
    assert figures["patch_share"] == pytest.approx((0 / (60 * 140) + 7 * 30 / grass) / 2)
    assert figures["kerb_per_mille"] == pytest.approx(1e3 * 32 / (2 * 60 * 160))
    figures = texture_figures(np.full((1, 80, 160, 3), 102, np.uint8))  # all road
    assert figures == dict(patch_share=None, kerb_per_mille=0.0)


def test_texture_follows_the_dream_against_the_recording():
    from drivesim_reference.futures import TEXTURE_STEPS, texture

    n = 80
    frames = carracing_frames(n)
    data = episodes.Episodes(frames, np.zeros((n, 2), np.float32), np.array([0]))
    codes = torch.arange(n, dtype=torch.float32)[:, None]
    decode = lambda z: frames[z[:, 0].round().long().clamp(0, n - 1).numpy()]  # noqa: E731
    faithful = texture(Dream(1.0), data, codes, torch.zeros(n, 2), decode, frames)
    assert faithful["steps"] == list(TEXTURE_STEPS) and faithful["windows"] == len(data.windows(35)[::10])
    assert faithful["mean"] == faithful["recorded"] == faithful["reconstruction"] and "sampled" not in faithful
    assert faithful["recorded"]["kerb_per_mille"][-1] > 0  # every window's 30th frame has the kerb
    still = texture(Dream(0.0), data, codes, torch.zeros(n, 2), decode, frames)  # the last seed frame, again
    # The first window's last seed frame (4) has no kerb, its next frame has.
    assert still["mean"]["kerb_per_mille"][0] < faithful["mean"]["kerb_per_mille"][0]
    assert still["mean"]["patch_share"][-1] < faithful["mean"]["patch_share"][-1]  # the patch grows


def test_texture_baselines_fit_a_linear_dream_and_copy_the_last_seed():
    from drivesim_reference.futures import futures_windows, linear_predictor, linear_rollout, texture

    n = 80
    frames = carracing_frames(n)
    data = episodes.Episodes(frames, np.zeros((n, 2), np.float32), np.array([0]))
    codes, actions = torch.arange(n, dtype=torch.float32)[:, None], torch.zeros(n, 2)
    decode = lambda z: frames[z[:, 0].round().long().clamp(0, n - 1).numpy()]  # noqa: E731
    # Codes one apart: the next code is the last plus one, a linear map the fit finds (all but
    # exactly without a ridge).
    z, c = futures_windows(data, codes, actions, 10)
    rolled = linear_rollout(linear_predictor(data, codes, actions, ridge=1e-9), z, c)
    assert rolled.shape == (len(z), z.shape[1] - 1, 1)
    assert torch.allclose(rolled, z[:, 1:], atol=1e-3)
    out = texture(Dream(1.0), data, codes, actions, decode, frames, reference=(data, codes, actions))
    # With the ridge the fitted step falls short by under a frame after 30 steps (0.76 for the
    # first window): the first step's frames are the recorded ones.
    assert [v[0] for v in out["linear"].values()] == [v[0] for v in out["recorded"].values()]
    still = texture(Dream(0.0), data, codes, actions, decode, frames)  # the mean rollout holds the last seed
    assert out["copy"] == still["mean"] != out["recorded"]
    short = episodes.Episodes(frames[:2], np.zeros((2, 2), np.float32), np.array([0]))  # no window of 3
    assert linear_predictor(short, codes[:2], actions[:2]) is None
    assert "linear" not in texture(Dream(1.0), data, codes, actions, decode, frames, reference=(short, codes[:2], actions[:2]))


def test_the_probe_against_the_real_car_gives_gaps_and_ratios():
    from drivesim import probe

    def figures(right_way, left, right):
        return dict(right_way=right_way, symmetry=right / left if left and right else None,
                    road_moves_px_left_steering=left, road_moves_px_right_steering=right, starts_with_road=9)

    dream = {"5": {"0.3": figures(0.9, 20.0, 15.0)}, "10": {"0.3": figures(0.5, None, None)}}
    real = {"5": {"0.3": figures(0.96, 25.0, 30.0)}, "10": {"0.3": figures(0.44, 10.0, 12.0)}}
    gaps = probe.against_real(dream, real)
    five = gaps["5"]["0.3"]
    assert five["right_way_gap_points"] == pytest.approx(-6.0)
    assert five["moves_left_steering"] == pytest.approx(0.8) and five["moves_right_steering"] == pytest.approx(0.5)
    assert five["symmetry"] == pytest.approx(0.75) and five["symmetry_real"] == pytest.approx(1.2)
    ten = gaps["10"]["0.3"]
    assert ten["right_way_gap_points"] == pytest.approx(6.0) and ten["moves_left_steering"] is None


def test_the_real_probe_is_computed_once_per_data_file(tmp_path, monkeypatch):
    """`probe_real.cached` reuses `DATA.probe-real.json` for the same bytes, and computes again
    when the file changes."""
    from drivesim.carracing import probe_real
    runs = []
    monkeypatch.setattr(probe_real, "real_probe", lambda path, workers: runs.append(path) or {"5": len(runs)})
    data = tmp_path / "held_out.safetensors.gz"
    data.write_bytes(b"one recording")
    assert probe_real.cached(data, 1, log=lambda *_: None) == {"5": 1}
    assert probe_real.cached(data, 1, log=lambda *_: None) == {"5": 1} and len(runs) == 1
    data.write_bytes(b"another recording")
    assert probe_real.cached(data, 1, log=lambda *_: None) == {"5": 2} and len(runs) == 2
    assert (tmp_path / "held_out.safetensors.gz.probe-real.json").exists()


class Steering(torch.nn.Module):
    """A dream whose one-number code is the steering summed since its start: every input counts."""

    def __init__(self):
        super().__init__()
        self.W = torch.zeros(1, 1)

    def forward(self, z, h, c):
        h = h + c[:, 1:2]
        return h, h


def test_steering_probe_steers_from_the_start_not_through_the_seed_frames():
    # The real probe (probe_real) drives the recording to the start, then steers: the dream's
    # seed frames must be stepped with the recorded actions (here straight), so that after k
    # steps of steering x the dream's code is k x. Feeding x through the 4 seed steps too made
    # it (4 + k) x: a hidden state that steered before the car did.
    from drivesim import probe
    from drivesim_reference.futures import steering_probe

    n = 60
    frames = np.zeros((n, 80, 160, 3), np.uint8)
    data = episodes.Episodes(frames, np.zeros((n, 2), np.float32), np.array([0]))

    def decode(z):  # the road 4 px left per unit of code, as right steering moves it
        out = np.zeros((len(z), 80, 160, 3), np.uint8)
        out[..., 1] = 200
        for i, centre in enumerate(80 - 4 * z[:, 0].numpy()):
            out[i, :, int(round(centre)) - 10:int(round(centre)) + 10] = 105
        return out

    probed = steering_probe(SimpleNamespace(transition=Steering()), data, torch.zeros(n, 1), torch.zeros(n, 2), decode)
    for k in (5, 10):
        for x in probe.PROBE_STEER:
            moved = probed[str(k)][str(x)]
            assert moved["road_moves_px_left_steering"] == pytest.approx(4 * k * x, abs=0.6)
            assert moved["road_moves_px_right_steering"] == pytest.approx(4 * k * x, abs=0.6)

"""The extension module on numpy arrays: shapes, dtypes, agreement with PyTorch's reference
outputs (the crate's parity fixtures), errors, and the interpreter released while it computes."""

import threading

import numpy as np
import pytest
from conftest import fixture, relative_error

import drivesim


def test_model_metadata(model):
    assert model.frame_shape == (80, 160, 3)
    assert (model.z_dim, model.hidden_dim, model.action_dim) == (128, 256, 2)
    assert model.frame_hz == 12.5
    names = [a["name"] for a in model.actions]
    assert names == ["speed", "steering"]
    assert model.actions[1]["min"] == -1.0 and model.actions[1]["max"] == 1.0
    assert model.config["z_dim"] == 128
    assert "z_dim=128" in repr(model)


def test_shapes_and_dtypes(model, clip):
    frames, actions = clip
    sim = drivesim.Simulator(model, batch=4)
    assert sim.batch == 4 and sim.threads == 1 and sim.isa in ("avx512", "avx2", "neon", "scalar")
    z = sim.encode(frames[:4])
    assert z.shape == (4, 128) and z.dtype == np.float32
    one = sim.encode(frames[0])
    assert one.shape == (128,)
    np.testing.assert_array_equal(one, z[0])  # bit-identical whatever the batch
    g = sim.generate(z)
    assert g.shape == (4, 80, 160, 3) and g.dtype == np.uint8
    gf = sim.generate(z, dtype=np.float32)
    assert gf.dtype == np.float32 and gf.min() >= -1 and gf.max() <= 1
    # 8-bit frames are the float frames rounded: (v + 1) * 127.5, half up.
    one, half, scale = np.float32(1), np.float32(0.5), np.float32(127.5)
    np.testing.assert_array_equal(((np.clip(gf, -1, 1) + one) * scale + half).astype(np.uint8), g)
    h0 = np.zeros((4, 256), np.float32)
    a = np.tile(np.float32([30.0, 0.1]), (4, 1))
    z1, h1 = sim.transition(z, h0, a)
    assert z1.shape == (4, 128) and h1.shape == (4, 256)
    assert not h0.any()  # the input is not changed
    z2, h2 = sim.transition_fed_back(h1, a)
    assert z2.shape == (4, 128) and not np.array_equal(h2, h1)


def test_uint8_frames_are_float_frames(model, clip):
    frames, _ = clip
    sim = drivesim.Simulator(model, batch=2)
    floats = (frames[:2].astype(np.float32) / 127.5 - 1.0).astype(np.float32)
    np.testing.assert_array_equal(sim.encode(frames[:2]), sim.encode(floats))


def test_rollouts_agree_with_steps(model, clip):
    frames, actions = clip
    sim = drivesim.Simulator(model, batch=4)
    codes, dreamed = sim.rollout(frames[:3], actions[:2 + 4], frames=True)
    assert codes.shape == (4, 128) and dreamed.shape == (4, 80, 160, 3)
    # The same by hand: teacher-forced through the seeds, then fed back.
    z = sim.encode(frames[:3])
    h = np.zeros(256, np.float32)
    for t in range(2):
        _, h = sim.transition(z[t], h, actions[t])
    step, h = sim.transition(z[2], h, actions[2])
    np.testing.assert_array_equal(step, codes[0])
    for t in range(1, 4):
        step, h = sim.transition_fed_back(h, actions[2 + t])
        np.testing.assert_array_equal(step, codes[t])
    np.testing.assert_array_equal(sim.generate(codes), dreamed)


def test_rollout_candidates(model, clip):
    frames, actions = clip
    sim = drivesim.Simulator(model, batch=3)
    z = sim.encode(frames[0])
    h = np.zeros(256, np.float32)
    plan = np.zeros((5, 3, 2), np.float32)
    plan[..., 0] = 30.0
    plan[..., 1] = [-0.5, 0.0, 0.5]
    codes = sim.rollout_candidates(h, plan, z=z)
    assert codes.shape == (5, 3, 128)
    # Each candidate gets the bits a rollout of its own would.
    step, hh = sim.transition(z, h, plan[0, 2])
    np.testing.assert_array_equal(step, codes[0, 2])
    step, _ = sim.transition_fed_back(hh, plan[1, 2])
    np.testing.assert_array_equal(step, codes[1, 2])
    codes2, pictures = sim.rollout_candidates(h, plan, z=z, frames=True, dtype="float32")
    np.testing.assert_array_equal(codes, codes2)
    assert pictures.shape == (5, 3, 80, 160, 3) and pictures.dtype == np.float32


@pytest.mark.parametrize("name", ["small_f32", "tall_f32", "wide_f32"])
def test_agrees_with_pytorch(name):
    """The crate's parity fixtures: PyTorch's outputs for the same weights and inputs."""
    safetensors = pytest.importorskip("safetensors.numpy")
    io = safetensors.load_file(fixture(f"{name}.io.safetensors"))
    model = drivesim.Model.load(fixture(f"{name}.safetensors"))
    sim = drivesim.Simulator(model, batch=8)
    assert relative_error(sim.encode(io["encode.frames"]), io["encode.mean"]) < 1e-4
    assert relative_error(sim.generate(io["generate.z"], dtype=np.float32), io["generate.frames"]) < 1e-4
    codes, frames = sim.rollout(io["rollout.seed_frames"], io["rollout.actions"], frames=True, dtype=np.float32)
    assert relative_error(codes, io["rollout.codes"]) < 1e-4
    assert relative_error(frames, io["rollout.frames"]) < 1e-4


def test_threads_give_the_same_bits(model, clip):
    frames, actions = clip
    one = drivesim.Simulator(model, batch=2, threads=1)
    two = drivesim.Simulator(model, batch=2, threads=2)
    np.testing.assert_array_equal(one.encode(frames[:2]), two.encode(frames[:2]))
    np.testing.assert_array_equal(one.rollout(frames[:3], actions[:8]), two.rollout(frames[:3], actions[:8]))


def test_bad_input_raises_typed_errors(model, clip, tmp_path):
    frames, _ = clip
    sim = drivesim.Simulator(model, batch=2)
    z = sim.encode(frames[:2])
    cases = [
        (ValueError, "float64", lambda: sim.encode(frames.astype(np.float64))),
        (ValueError, "shape", lambda: sim.encode(np.zeros((2, 3), np.uint8))),
        (ValueError, "at most 2", lambda: sim.encode(frames[:3])),
        (ValueError, "contiguous", lambda: sim.encode(frames[:2, :, ::-1])),
        (ValueError, "lie in [-1, 1]", lambda: sim.encode(np.full((80, 160, 3), 2.0, np.float32))),
        (ValueError, "NaN", lambda: sim.encode(np.full((80, 160, 3), np.nan, np.float32))),
        (ValueError, "list", lambda: sim.encode([1, 2, 3])),
        (ValueError, "int64", lambda: sim.generate(z, dtype=np.int64)),
        (ValueError, "leading", lambda: sim.transition(z, np.zeros((1, 256), np.float32), np.zeros((2, 2), np.float32))),
        (ValueError, "float32", lambda: sim.transition(z, np.zeros((2, 256)), np.zeros((2, 2), np.float32))),
        (ValueError, "actions", lambda: sim.rollout(frames[:3], np.zeros((2, 2), np.float32))),
        (ValueError, "safetensors", lambda: drivesim.Model.from_bytes(b"not a weight file")),
        (FileNotFoundError, "missing.safetensors", lambda: drivesim.Model.load(tmp_path / "missing.safetensors")),
        (MemoryError, "cannot allocate", lambda: drivesim.Simulator(model, batch=1 << 40)),
        (ValueError, "episodes", lambda: drivesim.load_episodes(__file__)),
    ]
    for kind, words, call in cases:
        with pytest.raises(kind) as raised:
            call()
        assert words in str(raised.value), (words, str(raised.value))
    with pytest.raises(OSError):
        drivesim.Model.load(tmp_path)  # a directory


def test_the_interpreter_runs_while_the_crate_computes(model, clip):
    """A long rollout in one thread; the main thread counts while it runs. Were the
    interpreter held, the count could not move during the call."""
    frames, actions = clip
    sim = drivesim.Simulator(model)
    plan = np.tile(actions[:1], (400, 1))
    started = threading.Event()

    def dream():
        started.set()
        sim.rollout(frames[:1], plan, frames=True)

    worker = threading.Thread(target=dream)
    worker.start()
    started.wait()
    count = 0
    while worker.is_alive():
        count += 1
    worker.join()
    assert count > 10_000


def test_one_simulator_is_not_shared_between_threads(model, clip):
    frames, actions = clip
    sim = drivesim.Simulator(model)
    plan = np.tile(actions[:1], (300, 1))
    errors = []

    def dream():
        try:
            sim.rollout(frames[:1], plan, frames=True)
        except RuntimeError as e:
            errors.append(e)

    threads = [threading.Thread(target=dream) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    # Either the calls did not overlap, or the second was told to use its own simulator.
    assert all("another thread" in str(e) for e in errors)


def test_act(model, clip):
    """The cloned driver's policy: shapes, the trained ranges, one item as in a batch, errors."""
    assert model.policy_width is not None
    sim = drivesim.Simulator(model, batch=4)
    z = sim.encode(clip[0][:4])
    h = np.random.default_rng(0).uniform(-1, 1, (4, model.hidden_dim)).astype(np.float32)
    actions = sim.act(z, h)
    assert actions.shape == (4, 2) and actions.dtype == np.float32
    for value, spec in zip(actions.T, model.actions):
        assert (value >= spec["min"]).all() and (value <= spec["max"]).all()
    np.testing.assert_array_equal(sim.act(z[2], h[2]), actions[2])
    with pytest.raises(ValueError, match="same leading"):
        sim.act(z, h[0])
    with pytest.raises(ValueError):
        sim.act(z[:, 1:], h)
    no_policy = drivesim.Model.load(fixture("small_f32.safetensors"))
    assert no_policy.policy_width is None
    small = drivesim.Simulator(no_policy)
    with pytest.raises(ValueError, match="no policy"):
        small.act(np.zeros(no_policy.z_dim, np.float32), np.zeros(no_policy.hidden_dim, np.float32))


def test_sampled_futures(model):
    # The small_f32 fixture's transition predicts its mean only; the spread_f32 fixture's and
    # the default model's also their spread.
    assert model.samples
    mean_only = drivesim.Model.load(fixture("small_f32.safetensors"))
    assert not mean_only.samples
    sim = drivesim.Simulator(mean_only)
    with pytest.raises(ValueError, match="spread"):
        sim.set_sampling(1.0, 3)
    sim.set_sampling(0.0, 3)
    spread = drivesim.Model.load(fixture("spread_f32.safetensors"))
    assert spread.samples
    rng = np.random.default_rng(0)
    h = (rng.standard_normal(spread.hidden_dim) * 0.5).astype(np.float32)
    z = rng.standard_normal(spread.z_dim).astype(np.float32)
    plans = np.zeros((6, 5, 2), np.float32)
    plans[..., 1] = np.linspace(-0.5, 0.5, 5)

    def futures(threads, temperature, seed):
        s = drivesim.Simulator(spread, batch=5, threads=threads)
        s.set_sampling(temperature, seed)
        assert s.sampling == (temperature, seed)
        return s.rollout_candidates(h, plans, z=z)

    mean = futures(1, 0.0, 9)
    np.testing.assert_array_equal(mean, drivesim.Simulator(spread, batch=5).rollout_candidates(h, plans, z=z))
    drawn = futures(1, 1.0, 9)
    assert not np.array_equal(drawn, mean)
    np.testing.assert_array_equal(futures(2, 1.0, 9), drawn)  # the seed's bits, whatever the threads
    assert not np.array_equal(futures(1, 1.0, 10), drawn)
    with pytest.raises(ValueError, match="temperature"):
        sim.set_sampling(-1.0, 3)
    env = drivesim.Environment(spread, drives=1, candidates=5)
    env.set_sampling(1.0, 4)


def test_texture_net_sampled_futures(model):
    """A file with the texture net (`transition.texture.*`, the texture_f32 fixture's, and the
    default's, 256 wide) samples through it: temperature 0 is the mean, a seed gives its bits at
    any thread count; a file without one has none."""
    textured = drivesim.Model.load(fixture("texture_f32.safetensors"))
    assert textured.texture_width == 9 and textured.samples and model.texture_width == 256
    assert drivesim.Model.load(fixture("small_f32.safetensors")).texture_width is None
    h = np.linspace(-0.5, 0.5, textured.hidden_dim, dtype=np.float32)
    z = np.linspace(-1.0, 1.0, textured.z_dim, dtype=np.float32)
    plans = np.zeros((4, 3, 2), np.float32)
    plans[..., 0], plans[..., 1] = 20.0, np.linspace(-0.3, 0.3, 3)

    def futures(threads, temperature):
        s = drivesim.Simulator(textured, batch=3, threads=threads)
        s.set_sampling(temperature, 5)
        return s.rollout_candidates(h, plans, z=z)

    mean, drawn = futures(1, 0.0), futures(1, 1.0)
    assert np.all(np.isfinite(drawn)) and not np.array_equal(drawn, mean)
    np.testing.assert_array_equal(futures(2, 1.0), drawn)


def test_correlated_sampled_futures(tmp_path):
    """A file with the noise factor (`transition.L`, here the spread_f32 fixture's, which PyTorch
    fitted) samples correlated noise: the same seed gives the same bits at any thread count,
    other bits than the independent noise, and temperature 0 is still the mean."""
    from safetensors import safe_open
    from safetensors.numpy import load_file, save_file

    path = fixture("spread_f32.safetensors")
    with safe_open(path, "numpy") as f:
        metadata = f.metadata()
    tensors = load_file(path)
    tensors["transition.L"] = load_file(fixture("spread_f32.train.safetensors"))["noise_factor"]
    save_file(tensors, str(tmp_path / "correlated.safetensors"), metadata=metadata)
    independent, correlated = drivesim.Model.load(path), drivesim.Model.load(tmp_path / "correlated.safetensors")
    assert correlated.samples_correlated and not independent.samples_correlated
    rng = np.random.default_rng(1)
    h = (rng.standard_normal(correlated.hidden_dim) * 0.5).astype(np.float32)
    z = rng.standard_normal(correlated.z_dim).astype(np.float32)
    plans = np.zeros((4, 3, 2), np.float32)

    def futures(model, threads, temperature):
        s = drivesim.Simulator(model, batch=3, threads=threads)
        s.set_sampling(temperature, 5)
        return s.rollout_candidates(h, plans, z=z)

    drawn = futures(correlated, 1, 1.0)
    np.testing.assert_array_equal(futures(correlated, 2, 1.0), drawn)
    assert not np.allclose(drawn, futures(independent, 1, 1.0))
    np.testing.assert_array_equal(futures(correlated, 1, 0.0), futures(independent, 1, 0.0))


def test_sample_is_the_rollouts_step_for_a_controller(model):
    """`Simulator.sample`: a step taken with `transition`, then sampled, is the first step of a
    rollout sampled with the same seed; the texture_f32 fixture's draws are PyTorch's."""
    sim = drivesim.Simulator(model, batch=2)
    h, z = np.zeros(model.hidden_dim, np.float32), np.linspace(-1, 1, model.z_dim, dtype=np.float32)
    action = np.float32([30.0, 0.2])
    z_mean, h_next = sim.transition(z, h, action)
    np.testing.assert_array_equal(sim.sample(h_next, 0, z_mean), z_mean)  # sampling off
    sim.set_sampling(1.0, 9)
    drawn = sim.sample(h_next, 0, z_mean)
    assert not np.array_equal(drawn, z_mean)
    rollout = sim.rollout_candidates(h, action[None, None], z=z)
    np.testing.assert_array_equal(drawn, rollout[0, 0])
    np.testing.assert_array_equal(z_mean, sim.transition(z, h, action)[0])  # codes not changed
    with pytest.raises(ValueError, match="leading dimensions"):
        sim.sample(h_next[None], 0, z_mean)
    with pytest.raises(ValueError, match="step"):
        sim.sample(h_next, -1, z_mean)
    with pytest.raises(TypeError, match="step"):
        sim.sample(h_next, "0", z_mean)
    with pytest.raises(ValueError):
        sim.sample(np.tile(h_next, (3, 1)), 0, np.tile(z_mean, (3, 1)))  # beyond the batch of 2

    io = pytest.importorskip("safetensors.numpy").load_file(fixture("texture_f32.io.safetensors"))
    textured = drivesim.Simulator(drivesim.Model.load(fixture("texture_f32.safetensors")), batch=5)
    textured.set_sampling(0.7, 3)
    got = textured.sample(io["h"], 4, io["mean"])
    error = np.linalg.norm(got - io["sampled"]) / np.linalg.norm(io["sampled"])
    assert error < 1e-5, error

"""drivesim.relabel: episodes labelled with a teacher's policy, for a policy carried to another
world model."""

import numpy as np
import pytest

import drivesim
from drivesim import episodes, relabel


def _data(n=(5, 3)):
    rng = np.random.default_rng(4)
    frames = rng.integers(0, 256, (sum(n), 80, 160, 3), dtype=np.uint8)
    actions = np.stack([rng.uniform(10, 50, sum(n)), rng.uniform(-0.5, 0.5, sum(n))], 1).astype(np.float32)
    return episodes.Episodes(frames, actions, np.array([0, n[0]], np.int64))


def test_labels_are_the_teachers_decisions_with_its_state_from_zeros_per_episode():
    model, data = drivesim.Model.load(), _data()
    got = relabel.labels(model, data, batch=3)  # a batch that does not divide the frames
    sim = drivesim.Simulator(model)
    for start, end in data.bounds():
        h = np.zeros(model.hidden_dim, np.float32)
        for t in range(start, end):
            z = sim.encode(data.frames[t])
            expected = sim.act(z, h)
            np.testing.assert_allclose(got[t], [expected[0], np.clip(expected[1], -1, 1)], rtol=1e-5, atol=1e-5)
            _, h = sim.transition(z, h, data.actions[t])
    assert got.dtype == np.float32 and got.shape == (8, 2)


def test_pace_labels_the_speed_with_the_teachers_pace_head_and_keeps_the_steering():
    model, data = drivesim.Model.load(), _data()
    plain, paced = relabel.labels(model, data), relabel.labels(model, data, pace=True)
    np.testing.assert_array_equal(paced[:, 1], plain[:, 1])
    sim = drivesim.Simulator(model)
    h = np.zeros(model.hidden_dim, np.float32)
    for t in range(data.bounds()[0][1]):
        z = sim.encode(data.frames[t])
        assert paced[t, 0] == pytest.approx(sim.pace(z, h)[0], rel=1e-5, abs=1e-4) != plain[t, 0]
        _, h = sim.transition(z, h, data.actions[t])


def test_the_command_writes_the_labels_and_keeps_the_rest(tmp_path, capsys):
    data = _data()
    episodes.write(tmp_path / "in.safetensors", data, {"source": "test"})
    out = tmp_path / "out.safetensors.gz"
    assert relabel.main([str(tmp_path / "in.safetensors"), "--out", str(out), "--threads", "1"]) == 0
    assert "8 frames in 2 episodes labelled" in capsys.readouterr().out
    back = episodes.read(out)
    np.testing.assert_array_equal(back.frames, data.frames)
    np.testing.assert_array_equal(back.actions, data.actions)
    np.testing.assert_array_equal(back.labels, relabel.labels(drivesim.Model.load(), data))
    assert episodes.metadata(out)["source"] == "test"


def test_a_teacher_without_a_policy_is_an_error_and_writes_nothing(tmp_path):
    from conftest import fixture

    episodes.write(tmp_path / "in.safetensors", _data())
    with pytest.raises(ValueError, match="no policy"):
        relabel.labels(drivesim.Model.load(fixture("small_f32.safetensors")), _data())
    with pytest.raises(SystemExit):
        relabel.main([str(tmp_path / "in.safetensors"), "--out", str(tmp_path / "x.safetensors"),
                      "--teacher", fixture("small_f32.safetensors")])
    assert not (tmp_path / "x.safetensors").exists()


def test_pace_from_a_teacher_without_a_pace_head_is_an_error(tmp_path):
    from pathlib import Path

    from safetensors import safe_open
    from safetensors.numpy import load_file, save_file

    path = Path(__file__).resolve().parents[2] / "weights/default.safetensors"
    with safe_open(path, "numpy") as f:
        metadata = f.metadata()
    tensors = {k: v for k, v in load_file(path).items() if not k.startswith("pace.")}
    save_file(tensors, str(tmp_path / "no_pace.safetensors"), metadata=metadata)
    teacher = drivesim.Model.load(tmp_path / "no_pace.safetensors")
    assert teacher.pace_width is None and teacher.policy_width is not None
    with pytest.raises(ValueError, match="no pace head"):
        relabel.labels(teacher, _data(), pace=True)
    with pytest.raises(TypeError, match="pace"):
        relabel.labels(drivesim.Model.load(), _data(), pace="yes")


def test_threads_below_one_are_refused(tmp_path):
    episodes.write(tmp_path / "in.safetensors", _data())
    with pytest.raises(SystemExit):
        relabel.main([str(tmp_path / "in.safetensors"), "--out", str(tmp_path / "x.safetensors"), "--threads", "0"])
    assert not (tmp_path / "x.safetensors").exists()

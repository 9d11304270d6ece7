"""Sampler files (drivesim.sampler): a texture net apart from its world. Written from a weight
file that is the world but for its texture net, it draws that file's futures in the world (the
mean dream the world's own); another world refuses it; the command writes nothing where it
fails; the built-in judge is the default's."""

import os

import numpy as np
import pytest
from conftest import REPO, fixture
from safetensors.numpy import load_file, save_file

import drivesim
from drivesim.driver import world_fingerprint
from drivesim.sampler import main, write_sampler

DEFAULT = os.path.join(REPO, "weights", "default.safetensors")
JUDGE = os.path.join(REPO, "weights", "judge.safetensors")


def futures(model, temperature):
    """Three steps of the transition from fixed states, each next code its mean (``temperature``
    0) or sampled."""
    sim = drivesim.Simulator(model, batch=4)
    sim.set_sampling(temperature, 3)
    rng = np.random.default_rng(1)
    h = np.tanh(rng.standard_normal((4, model.hidden_dim))).astype(np.float32)
    z = rng.standard_normal((4, model.z_dim)).astype(np.float32)
    actions = np.stack([np.full(4, 20.0), np.linspace(-0.4, 0.4, 4)], 1).astype(np.float32)
    out = []
    for step in range(3):
        z, h = sim.transition(z, h, actions)
        if temperature > 0:
            z = sim.sample(h, step, z)
        out.append(z)
    return np.stack(out)


def retextured(path, out):
    """The weight file at ``path`` with its texture net's values scaled: the same world, another sampler."""
    from safetensors import safe_open

    with safe_open(path, "numpy") as f:
        metadata = f.metadata()
    tensors = load_file(path)
    for name in [n for n in tensors if n.startswith("transition.texture.")]:
        tensors[name] = (tensors[name] * 0.5).astype(tensors[name].dtype)
    save_file(tensors, str(out), metadata=metadata)
    return out


def test_a_sampler_file_draws_the_futures_of_the_net_it_came_from(tmp_path):
    world = fixture("texture_f32.safetensors")
    other = retextured(world, tmp_path / "other.safetensors")
    out = tmp_path / "sampler.safetensors"
    assert write_sampler(other, world, out) == world_fingerprint(world)
    dreamt = drivesim.Model.load(world, sampler=out)
    own, original = drivesim.Model.load(world), drivesim.Model.load(other)
    assert np.array_equal(futures(dreamt, 1.0), futures(original, 1.0))
    assert not np.array_equal(futures(dreamt, 1.0), futures(own, 1.0))
    assert np.array_equal(futures(dreamt, 0.0), futures(own, 0.0))


def test_the_built_in_judge_is_the_default_dreamt_through_the_shipped_sampler():
    judge, own = drivesim.Model.judge(), drivesim.Model.load()
    assert np.array_equal(futures(judge, 1.2), futures(drivesim.Model.load(sampler=JUDGE), 1.2))
    assert not np.array_equal(futures(judge, 1.2), futures(own, 1.2))
    # Its read-out is the default's widened (drivesim.widen), so its mean dream is not the default's.
    assert not np.array_equal(futures(judge, 0.0), futures(own, 0.0))
    assert os.path.getsize(JUDGE) < 400_000  # the texture net and the read-out: 330 kB of the world's 15 MB


def test_another_world_refuses_a_sampler_and_the_command_writes_nothing(tmp_path, capsys):
    small, texture = fixture("small_f32.safetensors"), fixture("texture_f32.safetensors")
    with pytest.raises(ValueError, match="not in this weight file's world"):
        drivesim.Model.judge(texture)
    with pytest.raises(ValueError, match="not in this weight file's world"):
        drivesim.Model.load(texture, sampler=JUDGE)
    with pytest.raises(ValueError, match="not both"):
        drivesim.Model.load(driver=os.path.join(REPO, "weights", "dreamt.safetensors"), sampler=JUDGE)
    with pytest.raises(ValueError, match="not a sampler file"):
        drivesim.Model.load(sampler=DEFAULT)
    with pytest.raises(SystemExit) as exit:
        main([small, "--world", small, "--out", str(tmp_path / "never.safetensors")])  # no texture net
    assert exit.value.code == 2 and "cannot sample" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit:
        main([texture, "--world", DEFAULT, "--out", str(tmp_path / "never.safetensors")])  # another world
    assert exit.value.code == 2 and "not in this weight file's world" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_the_module_docstring_runs():
    import doctest

    import drivesim.sampler

    assert doctest.testmod(drivesim.sampler).failed == 0

"""Driver files (drivesim.driver): a driver apart from its world. Written from a weight file, it
drives in that world as the file's policy did, its pace head left out; another world refuses it;
the command writes nothing where it fails."""

import os

import numpy as np
import pytest
from conftest import REPO, fixture

import drivesim
from drivesim.carracing import make_agent
from drivesim.driver import main, world_fingerprint, write_driver

DEFAULT = os.path.join(REPO, "weights", "default.safetensors")


def test_a_driver_file_drives_as_the_policy_it_came_from(tmp_path):
    out = tmp_path / "clone.safetensors"
    assert write_driver(DEFAULT, out, world=DEFAULT) == world_fingerprint(DEFAULT)
    assert out.stat().st_size < 100_000  # the policy alone: 50 kB of the world's 15 MB
    driven, whole = drivesim.Model.load(driver=out), drivesim.Model.load()
    assert (driven.policy_width, driven.pace_width, whole.pace_width) == (64, None, 192)
    rng = np.random.default_rng(0)
    z = rng.standard_normal((9, 128)).astype(np.float32)
    h = np.tanh(rng.standard_normal((9, 256))).astype(np.float32)
    acts = [drivesim.Simulator(m, batch=9).act(z, h) for m in (driven, whole, drivesim.Model.dreamt())]
    assert np.array_equal(acts[0], acts[1]) and not np.array_equal(acts[0], acts[2])


def test_another_world_refuses_a_driver_and_the_command_writes_nothing(tmp_path, capsys):
    small, out = fixture("small_f32.safetensors"), tmp_path / "d.safetensors"
    write_driver(DEFAULT, out)
    with pytest.raises(ValueError, match=f"learnt in world {world_fingerprint(DEFAULT)}"):
        drivesim.Model.load(small, driver=out)
    with pytest.raises(ValueError, match="another world"):
        write_driver(DEFAULT, tmp_path / "never.safetensors", world=small)
    with pytest.raises(ValueError, match="not a driver file"):
        drivesim.Model.load(driver=DEFAULT)
    with pytest.raises(FileNotFoundError, match="missing"):
        drivesim.Model.load(driver=tmp_path / "missing.safetensors")
    with pytest.raises(TypeError):
        make_agent("dreamt", driver=3)
    with pytest.raises(SystemExit) as exit:
        main([small, "--out", str(tmp_path / "never.safetensors")])  # no policy
    assert exit.value.code == 2 and "no policy" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["d.safetensors"]

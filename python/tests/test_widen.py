"""Widened samplers (drivesim.widen): a sampler file that carries the world's read-out widened
about a mean code. Its mean dream is the world's spread by the factor about the centre, its
texture net the sampler's; the centre is the mean code of the frames and their mirror images;
by 1 gives the plain sampler back; the command refuses what it cannot use and writes nothing."""

import os

import numpy as np
import pytest
from conftest import fixture
from test_sampler import futures, retextured

import drivesim
from drivesim import episodes
from drivesim.sampler import write_sampler
from drivesim.widen import main, mean_code, widened_sampler

WORLD = fixture("texture_f32.safetensors")  # f32: its read-out is folded into the feedback too


@pytest.fixture
def sampler(tmp_path):
    out = tmp_path / "sampler.safetensors"
    write_sampler(retextured(WORLD, tmp_path / "other.safetensors"), WORLD, out)
    return out


def drives(path, n=40):
    """An episodes file of ``n`` random frames of the small world's size."""
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 256, (n, 16, 32, 3), dtype=np.uint8)
    actions = np.stack([np.full(n, 20.0), rng.uniform(-1, 1, n)], 1).astype(np.float32)
    episodes.write(path, episodes.Episodes(frames, actions, np.array([0, n // 2], np.int64)))
    return path, frames


def test_the_mean_dream_is_the_worlds_widened_about_the_centre_and_the_futures_the_samplers(tmp_path, sampler):
    centre = np.linspace(-0.5, 0.5, 12)
    out = tmp_path / "widened.safetensors"
    out.write_bytes(widened_sampler(sampler, WORLD, centre, 1.2))
    wide, plain = drivesim.Model.load(WORLD, sampler=out), drivesim.Model.load(WORLD, sampler=sampler)
    rng = np.random.default_rng(2)
    h = np.tanh(rng.standard_normal((4, 40))).astype(np.float32)
    z = rng.standard_normal((4, 12)).astype(np.float32)
    actions = np.stack([np.full(4, 20.0), np.linspace(-0.4, 0.4, 4)], 1).astype(np.float32)
    (z_wide, h_wide), (z_own, h_own) = (drivesim.Simulator(m, batch=4).transition(z, h, actions) for m in (wide, plain))
    assert np.array_equal(h_wide, h_own)  # the read-out only moves the code
    assert np.allclose(z_wide, centre + 1.2 * (z_own - centre), atol=1e-5)
    # The widened codes are fed back, so the futures part from the plain sampler's from there on.
    assert not np.allclose(futures(wide, 1.0), futures(plain, 1.0))
    # By 1 the read-out is the world's, and the file the plain sampler's, byte for byte.
    assert widened_sampler(sampler, WORLD, centre, 1.0) == sampler.read_bytes()


def test_the_centre_is_the_mean_code_of_the_frames_and_their_mirror_images(tmp_path):
    path, frames = drives(tmp_path / "d.safetensors.gz")
    sim = drivesim.Simulator(drivesim.Model.load(WORLD), batch=len(frames))
    both = np.concatenate([sim.encode(frames), sim.encode(np.ascontiguousarray(frames[:, :, ::-1]))])
    assert np.allclose(mean_code(WORLD, path), both.astype(np.float64).mean(0), atol=1e-6)


def test_the_command_writes_the_widened_sampler_and_refuses_what_it_cannot_use(tmp_path, sampler, capsys):
    path, _ = drives(tmp_path / "d.safetensors.gz")
    out = tmp_path / "out" / "w.safetensors"
    out.parent.mkdir()
    assert main([str(sampler), "--world", WORLD, "--about", str(path), "--by", "1.1", "--out", str(out)]) == 0
    assert out.read_bytes() == widened_sampler(sampler, WORLD, mean_code(WORLD, path), 1.1)
    assert "widened 1.1x" in capsys.readouterr().out
    never = str(tmp_path / "out" / "never.safetensors")
    bad = [
        ["--by", "0"], ["--by", "nan"], ["--by", "-1"],
        ["--about", str(tmp_path / "missing.safetensors.gz")],  # no such file
        ["--about", WORLD],  # not an episodes file
        ["--world", fixture("small_f32.safetensors")],  # another world's sampler
    ]
    for change in bad:
        args = {"--world": WORLD, "--about": str(path), "--by": "1.1", **dict([change])}
        with pytest.raises(SystemExit) as exit:
            main([str(sampler), *[x for kv in args.items() for x in kv], "--out", never])
        assert exit.value.code == 2, change
    assert not os.path.exists(never)
    with pytest.raises(ValueError, match="centre"):
        widened_sampler(sampler, WORLD, np.zeros(5), 1.1)


def test_the_module_docstring_runs():
    import doctest

    import drivesim.widen

    assert doctest.testmod(drivesim.widen).failed == 0

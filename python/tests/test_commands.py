"""`python -m drivesim`: the one entry point of the package's tools (drivesim/__main__.py)."""

import subprocess
import sys

import pytest

from drivesim.__main__ import COMMANDS, main


def run(*args):
    return subprocess.run([sys.executable, "-m", "drivesim", *args], capture_output=True, text=True, timeout=120)


def test_help_lists_every_command(capsys):
    assert main(["help"]) == 0
    out = capsys.readouterr().out
    assert all(f"  {name} " in out for name in COMMANDS)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_each_command_answers_help(name):
    pytest.importorskip("Box2D")  # the CarRacing tools import gymnasium's Box2D at the top
    if name == "convert-comma":
        pytest.importorskip("h5py")
    done = run(name, "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: "), done.stdout[:200]
    assert done.stderr == ""


def test_no_command_or_an_unknown_one_is_a_usage_error(capsys):
    assert main([]) == 2
    assert main(["drive-fast"]) == 2
    assert "no such command: drive-fast" in capsys.readouterr().err
    done = run("drive-fast")
    assert done.returncode == 2 and "usage: python -m drivesim COMMAND" in done.stderr


def test_a_command_s_bad_arguments_are_its_usage_error():
    pytest.importorskip("Box2D")
    done = run("record", "--seeds", "x-y")
    assert done.returncode == 2
    assert "python -m drivesim record: error:" in done.stderr and "Traceback" not in done.stderr

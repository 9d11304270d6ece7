"""`python -m drivesim probe-real` (drivesim.carracing.probe_real's command line)."""

import json

import pytest

pytest.importorskip("Box2D")
from drivesim.carracing import probe_real  # noqa: E402 (after the skip: it needs gymnasium's Box2D)


def test_the_command_writes_the_cache_that_train_eval_reads(tmp_path, monkeypatch, capsys):
    data = tmp_path / "held.safetensors.gz"
    data.write_bytes(b"recorded episodes")
    runs = []
    monkeypatch.setattr(probe_real, "real_probe", lambda path, workers: runs.append(path) or {"5": {"0.3": 1.0}})
    probe_real.main(["--data", str(data), "--workers", "1", "--out", str(tmp_path / "figures.json")])
    assert json.loads((tmp_path / "figures.json").read_text()) == {"5": {"0.3": 1.0}}
    assert json.loads(capsys.readouterr().out) == {"5": {"0.3": 1.0}}
    # `train eval --probe-real` (probe_real.cached) now finds the figures without driving again.
    assert probe_real.cached(str(data), 1, log=lambda *_: None) == {"5": {"0.3": 1.0}} and len(runs) == 1

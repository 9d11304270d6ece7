"""The data behind the planners' speed model (drivesim.carracing.speed_model): the default's clone driving a
short stretch of a track, the model's error against the target's. Needs the drivesim package
with CarRacing: skipped without it."""

import numpy as np
import pytest

pytest.importorskip("Box2D")
from drivesim.carracing import speed_model  # noqa: E402 (after the skip: it needs Box2D)


def test_the_model_predicts_the_speed_a_decision_later_better_than_the_target():
    rows = speed_model.drive(None, [6000], frames=400)
    assert rows.shape[1] == 3 and len(rows) > 40
    speed, target, later = rows.T
    assert (np.abs(later - speed) < 10).mean() > 0.9  # a decision is 4 frames: no jumps
    model, as_target = speed_model.rms_errors(rows)
    assert model < 0.5 * as_target, (model, as_target)


def test_the_command_prints_the_bands_and_the_errors(capsys):
    assert speed_model.main(["--seeds", "6000", "--frames", "200"]) == 0
    out = capsys.readouterr().out
    assert "decisions on the road" in out and "0..   4" in out and "RMS error" in out


def test_nothing_to_measure_is_a_clear_exit():
    with pytest.raises(SystemExit, match="no decision on the road"):
        speed_model.main(["--seeds", "6000", "--frames", "20"])  # still warming up

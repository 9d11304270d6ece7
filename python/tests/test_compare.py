"""Tests of ``python -m drivesim compare``: scores paired by track from the scoring commands' output."""

import numpy as np
import pytest

from drivesim.carracing import compare

EVALUATE = """ track   reward frames  tiles on road ms/decision
  5000    920.0    800 100.0%  100.0%        2.50
  5001    700.5   1000  70.0%   60.0%        2.40
  5101    910.0    900 100.0%  100.0%        2.40
cloned: 843.5 ± 101.4 over 3 tracks (min 700.5, max 920.0); 2.43 ms per decision
"""
RECORD = "seed 5000: 925.0\nseed 5001: 915.5\nseed 5102: 930.0\nexpert: 920.2 ± 4.0 over 3 tracks\n"


def test_scores_read_both_commands_output():
    assert compare.scores(EVALUATE) == {5000: 920.0, 5001: 700.5, 5101: 910.0}
    assert compare.scores(RECORD) == {5000: 925.0, 5001: 915.5, 5102: 930.0}
    assert compare.scores("16\nModel name: x\n") == {}


def test_compare_pairs_by_track():
    """Only the tracks both drove; the difference's mean, its standard error and the > 30 tracks."""
    report = compare.compare(compare.scores(EVALUATE), compare.scores(RECORD), names=("cloned", "expert"))
    d = np.array([920.0 - 925.0, 700.5 - 915.5])
    assert report.startswith("2 tracks in common")
    assert f"{d.mean():+.1f} ± {d.std(ddof=1) / np.sqrt(2):.1f} (standard error)" in report
    assert "more than 30 behind on 1 [5001]" in report and "under 800: 1" in report
    assert "histogram of cloned: < 800: 1, 800-880: 0, 880-900: 0, 900-910: 0, 910-920: 0, 920-930: 1, >= 930: 0" in report
    assert compare.histogram(np.array([799.9, 800.0, 929.9, 930.0, 1000.0])).endswith("920-930: 1, >= 930: 2")
    many = compare.compare({t: 900.0 + t % 7 for t in range(200)}, {t: 900.0 for t in range(200)}, block=100)
    assert "0-99 (100)" in many and "100-199 (100)" in many
    with pytest.raises(ValueError, match="no track in common"):
        compare.compare({1: 900.0}, {2: 900.0})


def test_compare_command(tmp_path, capsys):
    first, second = tmp_path / "a.txt", tmp_path / "b.txt"
    first.write_text(EVALUATE)
    second.write_text(RECORD)
    assert compare.main([str(first), str(second)]) == 0
    assert "2 tracks in common" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="compare: .*missing"):
        compare.main([str(first), str(tmp_path / "missing.txt")])
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(SystemExit, match="compare"):
        compare.main([str(first), str(tmp_path / "bin.txt")])
    (tmp_path / "empty.txt").write_text("nothing here\n")
    with pytest.raises(SystemExit, match="no track in common"):
        compare.main([str(first), str(tmp_path / "empty.txt")])

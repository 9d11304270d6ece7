"""Rank reports pooled over their tracks (``python -m drivesim.carracing.rank_pool``): the pooled
gap and its error are those of the tracks side by side, and a report that cannot be pooled is
refused with its name."""

import json

import numpy as np
import pytest

from drivesim.carracing import rank_figures, rank_pool
from drivesim.carracing.family import Driver

FAMILY = [Driver("clone"), Driver("bias +0.2", bias=0.2)]


def write_report(path, seeds, real_off, dream_off, family=FAMILY, **settings):
    """A rank report as `rank` writes it, from ``(drivers, tracks)`` shares (windows and whole drives
    alike), with the dream's ``settings``."""
    scores = np.tile(np.arange(len(family), 0, -1.0)[:, None], len(seeds))
    figures = rank_figures.summary(family, scores, np.asarray(real_off), scores, np.asarray(dream_off))
    path.write_text(json.dumps({**figures, "seeds": list(seeds), "windows": figures, **settings}))
    return str(path)


def test_the_pooled_gap_and_its_error_are_the_tracks_side_by_side(tmp_path):
    rng = np.random.default_rng(0)
    real, dream = rng.uniform(0, 1, (2, 2, 5))
    a = write_report(tmp_path / "a.json", range(100, 102), real[:, :2], dream[:, :2])
    b = write_report(tmp_path / "b.json", range(200, 203), real[:, 2:], dream[:, 2:])
    out = rank_pool.pooled([a, b])
    assert out["tracks"] == 5
    se = rank_figures.off_road_gap_error(real, dream)
    assert [d["gap"] for d in out["drivers"]] == pytest.approx(dream.mean(1) - real.mean(1))
    assert [d["gap_se"] for d in out["drivers"]] == pytest.approx(se)
    assert [d["driver"] for d in out["drivers"]] == ["clone", "bias +0.2"]


def test_a_gap_just_past_the_bound_is_shown_outside_only_with_tracks_enough(tmp_path):
    # The pull is over by 0.12 on every track, give or take 0.02: past 0.1 by one error on 2
    # tracks, by more than three on 12.
    wobble = np.array([0.02, -0.02] * 6)
    real = np.zeros((2, 12))
    dream = np.stack([np.zeros(12), 0.12 + wobble])
    few = write_report(tmp_path / "few.json", range(2), real[:, :2], dream[:, :2])
    assert rank_pool.pooled([few])["shown_outside"] == 0
    paths = [write_report(tmp_path / f"{i}.json", range(10 * i, 10 * i + 2), real[:, 2 * i:2 * i + 2],
                          dream[:, 2 * i:2 * i + 2]) for i in range(6)]
    out = rank_pool.pooled(paths)
    assert (out["within"], out["shown_outside"]) == (1, 1)


def test_reports_that_cannot_be_pooled_are_refused_with_their_names(tmp_path, capsys):
    real = np.zeros((2, 2))
    good = write_report(tmp_path / "good.json", [1, 2], real, real)
    other = write_report(tmp_path / "other.json", [3, 4], real, real, family=[Driver("clone"), Driver("gain 2", gain=2.0)])
    again = write_report(tmp_path / "again.json", [2, 3], real, real)
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"seeds": [5], "windows": {"drivers": []}}))
    report = json.loads(open(good).read())
    report["windows"]["off_road_per_track"]["real"][0][0] = float("nan")
    nan = tmp_path / "nan.json"
    nan.write_text(json.dumps(report))
    report["seeds"], report["windows"]["off_road_per_track"] = [], {"real": [[], []], "dream": [[], []]}
    none = tmp_path / "none.json"
    none.write_text(json.dumps(report))
    (tmp_path / "broken.json").write_text("{")
    (tmp_path / "list.json").write_text("[]")
    cases = {str(tmp_path / "missing.json"): "not a readable", str(tmp_path / "broken.json"): "not a readable",
             str(tmp_path / "list.json"): "no windows", str(old): "made before", str(nan): "not one finite", str(none): "no tracks",
             other: "another family", again: r"tracks \[2\]"}
    for path, said in cases.items():
        with pytest.raises(ValueError, match=said):
            rank_pool.pooled([good, path] if path in (other, again) else [path])
        with pytest.raises(SystemExit) as e:
            rank_pool.main([good, path] if path in (other, again) else [path])
        assert e.value.code == 2 and path in capsys.readouterr().err
    with pytest.raises(ValueError, match="no whole drives"):
        rank_pool.pooled([str(tmp_path / "list.json")], whole=True)


def test_reports_dreamt_otherwise_are_not_pooled(tmp_path):
    """The same real drives read with another dream's settings (here: the futures' middle half, or
    another temperature) are refused; a report made before `rank` wrote the read is the mean's."""
    real = np.zeros((2, 2))
    judged = dict(judge=True, temperature=0.7, futures=16)
    mean = write_report(tmp_path / "mean.json", [1, 2], real, real, **judged, off_road_read="mean")
    before = write_report(tmp_path / "before.json", [3, 4], real, real, **judged)
    middle = write_report(tmp_path / "middle.json", [5, 6], real, real, **judged, off_road_read="midmean")
    colder = write_report(tmp_path / "colder.json", [7, 8], real, real, **{**judged, "temperature": 0.5})
    assert rank_pool.pooled([mean, before])["tracks"] == 4
    with pytest.raises(ValueError, match=r"middle.json: dreamt otherwise than .*mean.json "
                                         r"\(off_road_read 'midmean', not 'mean'\)"):
        rank_pool.pooled([mean, middle])
    with pytest.raises(ValueError, match=r"temperature 0.5, not 0.7"):
        rank_pool.pooled([before, colder])


def test_the_command_prints_and_writes_the_pooled_figures(tmp_path, capsys):
    real, dream = np.zeros((2, 3)), np.array([[0.0, 0.0, 0.0], [0.3, 0.2, 0.25]])
    a = write_report(tmp_path / "a.json", [7, 8, 9], real, dream)
    assert rank_pool.main([a, "--whole", "--report", str(tmp_path / "pooled.json")]) == 0
    assert "3 tracks: within 0.1 of the real share 1 of 2 drivers" in capsys.readouterr().out
    written = json.loads((tmp_path / "pooled.json").read_text())
    assert written["whole"] and written["drivers"][1]["gap"] == pytest.approx(0.25)

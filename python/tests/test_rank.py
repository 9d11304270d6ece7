"""The rank probe (``python -m drivesim.carracing.rank``): the rank figures, and a small family
on two short tracks end to end, killed and resumed to the same report (the dream batch:
``test_rank_dream.py``)."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import fixture

import drivesim
from drivesim.carracing import rank, rank_figures, rank_real
from drivesim.carracing.family import SMALL, Driver


def test_the_dreams_doubt_against_its_error():
    """Each driver's spread over the futures is reported, and its correlation over the family
    with the dream's error in ranks: here the dream doubts most where it ranks a driver
    farthest from its real place."""
    family = [Driver(n) for n in "abcd"]
    real = np.array([[900.0, 880.0], [100.0, 120.0], [500.0, 500.0], [300.0, 300.0]])
    dreamt = np.array([[4.0], [3.0], [2.0], [1.0]]) * np.ones((4, 2))  # ranks: 3 2 1 0, real: 3 0 2 1
    off = np.zeros((4, 2))
    spread = np.stack([np.array([[0.0], [20.0], [10.0], [10.0]]) * np.ones((4, 2)), off + 0.1])
    s = rank_figures.summary(family, real, off, dreamt, off, spread)
    assert s["doubt_against_error"] == pytest.approx(1.0)
    assert [d["dream_spread"] for d in s["drivers"]] == [0.0, 20.0, 10.0, 10.0]
    assert [d["dream_off_road_spread"] for d in s["drivers"]] == pytest.approx([0.1] * 4)
    assert "doubt_against_error" not in rank_figures.summary(family, real, off, dreamt, off)
    assert "spread" in rank_figures.doubt(s) and rank_figures.doubt(s["drivers"][1]).split() == ["20.0", "10.0%"]


def test_spearman_and_regret():
    assert rank_figures.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert rank_figures.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    np.testing.assert_allclose(rank_figures.ranks(np.array([5.0, 1.0, 5.0])), [1.5, 0.0, 1.5])
    family = [Driver(n) for n in "abc"]
    real = np.array([[900.0, 880.0], [100.0, 120.0], [500.0, 500.0]])
    dreamt = np.array([[1.0, 1.0], [3.0, 3.0], [2.0, 2.0]])  # ranks them backwards
    off = np.zeros((3, 2))
    s = rank_figures.summary(family, real, off, dreamt, off + 0.25)
    assert s["spearman"] == pytest.approx(-1.0)
    assert s["favourite"] == "b"
    assert s["regret_at_1"] == pytest.approx(1.0)
    assert s["off_road_gap"] == pytest.approx(0.25)


def test_a_dreamt_pull_is_read_as_the_real_pull_that_leaves_the_road_as_often():
    family = [Driver("clone"), Driver("+0.2", bias=0.2), Driver("+0.3", bias=0.3), Driver("-0.2", bias=-0.2),
              Driver("+0.2 fast", bias=0.2, speed=1.2)]
    real = np.array([0.0, 0.1, 0.7, 0.3, 0.5])
    dreamt = np.array([0.0, 0.4, 0.9, 0.15, 0.9])
    pulls = {p["driver"]: p for p in rank_figures.equivalent_pulls(family, real, dreamt)}
    assert set(pulls) == {"+0.2", "+0.3", "-0.2"}  # the fast pull changes two things: not on the curve
    assert pulls["+0.2"]["equivalent"] == pytest.approx(0.25)  # 0.4 is halfway from 0.1 at +0.2 to 0.7 at +0.3
    assert pulls["+0.3"]["equivalent"] is None  # beyond the strongest real pull's share
    assert pulls["-0.2"]["equivalent"] == pytest.approx(-0.1)  # the clone's 0 at 0, 0.3 at -0.2
    flat = rank_figures.equivalent_pulls(family[:3], np.array([0.05, 0.05, 0.7]), np.array([0.0, 0.05, 0.7]))
    assert flat[0]["equivalent"] == pytest.approx(0.2)  # on a flat stretch, the point nearest its own pull
    assert rank_figures.equivalent_pulls(family[:1], real[:1], dreamt[:1]) == []
    scores = np.tile(np.arange(3.0)[:, None], 2)  # (drivers, tracks)
    shares = [np.tile(np.array(x)[:, None], 2) for x in ([0.0, 0.1, 0.7], [0.0, 0.25, 0.9])]
    s = rank_figures.summary(family[:3], scores, shares[0], scores, shares[1])
    # +0.2 is 0.15 over in share, but its share is the real car's at +0.225: within 0.03 in pull
    assert s["pulls"][0]["equivalent"] == pytest.approx(0.225)
    assert (s["within"], s["within_or_pull"]) == (1, 2)


def test_an_off_road_gap_is_outside_the_bound_only_beyond_two_standard_errors_paired_by_track():
    family = [Driver("steady"), Driver("scattered")]
    real_off = np.full((2, 4), 0.3)
    dream_off = real_off + np.array([[0.2, 0.2, 0.2, 0.2], [0.5, -0.1, 0.3, -0.2]])
    se = rank_figures.off_road_gap_error(real_off, dream_off)
    np.testing.assert_allclose(se, [0.0, np.std([0.5, -0.1, 0.3, -0.2], ddof=1) / 2], atol=1e-12)
    scores = np.zeros((2, 4))
    s = rank_figures.summary(family, scores + [[1.0], [0.0]], real_off, scores, dream_off)
    # Both are outside 0.1; only the steady one's 0.2 is beyond what the tracks' spread explains.
    assert (s["within"], s["shown_outside"]) == (0, 1)
    assert [d["off_road_gap_se"] for d in s["drivers"]] == pytest.approx(se)
    np.testing.assert_allclose(s["off_road_per_track"]["dream"], dream_off)
    assert "±" in rank_figures.gap_text(s["drivers"][1]) and "+12.5%" in rank_figures.gap_text(s["drivers"][1])
    assert np.isnan(rank_figures.off_road_gap_error(real_off[:, :1], dream_off[:, :1])).all()  # one track


def test_a_window_cut_short_keeps_its_last_flag_to_the_horizon():
    np.testing.assert_array_equal(rank_real.padded_to_horizon([[0, 1, 1, 0], [0, 1]], 4), [[0, 1, 1, 0], [0, 1, 1, 1]])


def test_leaving_the_road_and_coming_back_and_the_bend_where_the_car_leaves():
    """Per driver: the windows that leave the road, the decisions off from the first leaving on,
    and in the ``memory`` decisions after a first leaving within the view's reach or past it (the
    dream's chance read as off above one half), and the behaviour drive's steering over the
    decisions up to the first leaving; the counts add over tracks and futures."""
    off = np.array([[[0, 1, 1, 0, 0], [0, 0, 0, 0, 0]],  # leaves at 1, within the view: off 2 of 4 after, 2 of 2 soon
                    [[0, 0, 0, 0.6, 0.7], [0.9, 0.2, 0.2, 0.2, 0.4]]])  # leaves at 3, past it (2 of 2); at 0 (1 of 5, 1 of 2)
    counts = rank_figures.leaving_counts(off, memory=2)
    np.testing.assert_array_equal(counts, [[2, 1, 4, 2, 2, 2, 0, 0], [2, 2, 7, 3, 2, 1, 2, 2]])
    road = np.array([[0.1, -0.1, 0.3, 0.3, 0.3], [-0.2, 0.0, 0.0, 0.0, 0.0]])
    bends = rank_figures.bend_sums(off, road, before=1)
    np.testing.assert_allclose(bends, [[0.0, 1], [0.3 - 0.2, 2]])  # the first: (0.1 - 0.1) / 2; the second: 0.3, -0.2
    family = [Driver("a"), Driver("b", bias=0.2)]
    figures = rank_figures.leaving(family, counts, counts + counts, bends, road.mean(), memory=2)
    assert figures["memory"] == 2  # the counts' own, as printed
    a, b = figures["drivers"]
    assert a["real"] == a["dream"] == {"leaves": 0.5, "off_after": 0.5, "off_after_in_view": 1.0,
                                       "off_after_past_view": None}
    assert b["real"] == {"leaves": 1.0, "off_after": pytest.approx(3 / 7), "off_after_in_view": 0.5,
                         "off_after_past_view": 1.0}
    assert a["bend_where_real_leaves"] == 0.0 and b["bend_where_real_leaves"] == pytest.approx(0.05)
    assert figures["road_steering"] == pytest.approx(0.07)
    never = rank_figures.leaving(family, np.array([[2, 0, 0, 0, 0, 0, 0, 0.0]] * 2), counts, np.zeros((2, 2)), 0.0)
    assert never["drivers"][0]["real"]["off_after"] is None and never["drivers"][0]["bend_where_real_leaves"] is None


def test_road_memory_is_the_correlation_step_by_step():
    rng = np.random.default_rng(3)
    real = rng.standard_normal((50, 4))
    dreamt = real.copy()
    dreamt[:, 2] = rng.standard_normal(50)  # the dream's road parts from the real one at step 3
    dreamt[:, 3] = 0.0  # and stops varying
    memory = rank.road_memory(dreamt, real)
    assert memory[:2] == pytest.approx([1.0, 1.0]) and abs(memory[2]) < 0.4 and np.isnan(memory[3])


def test_made_up_roads_compare_the_steering_past_the_road_memory():
    real = np.tile([0.0, 0.1, -0.1], (4, 6))[:, :16]  # (4 starts, 16 decisions): |s| 2/30 a decision on average
    dreamt = real.copy()
    dreamt[:, 10:] *= 2.0  # the made-up roads twice as curvy, the known ones as the real
    m = rank.made_up_roads(dreamt, real)
    assert m["after"] == 10 and m["dream"] == pytest.approx(2 * m["real"]) and m["real"] > 0
    assert m["dream_change"] == pytest.approx(2 * m["real_change"])
    # both bend either way a third of the time: twice as curvy is not bent more often
    assert m["real_left"] == pytest.approx(1 / 3, abs=0.04) and m["real_right"] == pytest.approx(1 / 3, abs=0.04)
    assert m["dream_left"] == m["real_left"] and m["dream_right"] == m["real_right"]
    dreamt[:, 10:] = -0.06  # a made-up road that only bends left
    m = rank.made_up_roads(dreamt, real)
    assert m["dream_left"] == 1.0 and m["dream_right"] == 0.0
    assert rank.made_up_roads(dreamt[:, :11], real[:, :11]) is None  # no decision past the memory to compare


def test_each_familys_drives_are_kept_under_their_own_names():
    """Families share ``--out`` (and the behaviour drive): driver 1 of ``small`` is not driver 1
    of ``all``, so a run of one never reads the other's drives; ``all`` keeps its old names."""
    from types import SimpleNamespace

    names = {f: rank_real.drive_name(SimpleNamespace(family_name=f), 1, 7) for f in rank.FAMILIES}
    assert names["all"] == "1_7.json" and len(set(names.values())) == len(names)


def test_the_learnt_family_is_the_failure_data_s_own_and_the_command_line_takes_it(tmp_path, capsys):
    """``--family learnt`` drives the failure data's own drivers (those the judge learnt from), not
    one of the probe's families, and the parser takes it where it refuses a family it does not know
    (each run stopped at a bad --horizon, before any drive)."""
    from drivesim.carracing import failures

    assert rank.FAMILIES["learnt"] == failures.training_family()
    assert all(rank.FAMILIES[f] == rank.PROBE_FAMILIES[f] for f in rank.PROBE_FAMILIES)
    assert {d.name for d in rank.FAMILIES["learnt"][1:]}.isdisjoint(d.name for d in rank.FAMILY)
    for family in ("learnt", "nobody"):
        with pytest.raises(SystemExit):
            rank.main(["--seeds", "1", "--out", str(tmp_path), "--family", family, "--horizon", "0"])
        said = capsys.readouterr().err
        assert ("invalid choice" in said) == (family == "nobody"), said


def _probe(out, *extra):
    pytest.importorskip("Box2D")
    command = [sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "3,4", "--out", str(out), "--family",
               "small", "--frames", "160", "--horizon", "4", "--starts", "2", *extra]
    return command


def _report(out):
    with open(os.path.join(out, "rank.json")) as f:
        report = json.load(f)
    report.pop("dream_decisions_per_second")
    return report


def test_a_small_family_end_to_end_and_resumed_after_a_kill(tmp_path):
    whole = tmp_path / "whole"
    subprocess.run(_probe(whole), check=True, capture_output=True, timeout=600)
    report = _report(whole)
    assert [d["driver"]["name"] for d in report["drivers"]] == [d.name for d in SMALL]
    for d in report["drivers"]:
        assert np.isfinite([d["real"], d["dream"], d["real_off_road"], d["dream_off_road"]]).all()
        assert 0 <= d["dream_off_road"] <= 1 and 0 <= d["real_off_road"] <= 1
    assert len(report["per_track"]["real"][0]) == 2
    assert len(report["road_memory"]) == 4 and report["road_memory"][0] == pytest.approx(1.0, abs=1e-5)
    assert report["made_up_roads"] is None  # 4 decisions: all within the road memory
    # The same real drives, the dream sampled three times from each start: no drive again.
    futures = subprocess.run(_probe(whole, "--temperature", "1", "--futures", "3", "--report", "futures.json"),
                             check=True, capture_output=True, text=True, timeout=600)
    assert "on track" in futures.stdout and "spread against the dream's error in ranks" in futures.stdout
    with open(whole / "futures.json") as f:
        sampled = json.load(f)
    assert sampled["futures"] == 3 and all(d["dream_spread"] >= 0 for d in sampled["drivers"])
    # The judge's futures: the same real drives, another dream.
    subprocess.run(_probe(whole, "--judge", "--report", "judge.json"), check=True, capture_output=True, timeout=600)
    subprocess.run(_probe(whole, "--temperature", "1.2", "--report", "own.json"), check=True, capture_output=True,
                   timeout=600)
    with open(whole / "judge.json") as f, open(whole / "own.json") as g:
        judged, own = json.load(f), json.load(g)
    assert judged["judge"] and not own["judge"] and judged["per_track"]["real"] == own["per_track"]["real"]
    assert judged["per_track"]["dream"] != own["per_track"]["dream"]
    # The judge dreams with its own settings unless told otherwise.
    assert judged["world_steering"] == list(rank.JUDGE_STEERING) != [1.0, 0.0] and own["world_steering"] == [1.0, 0.0]
    assert (judged["temperature"], judged["futures"], judged["off_road_read"]) \
        == (rank.JUDGE_TEMPERATURE, rank.JUDGE_FUTURES, rank.JUDGE_OFF_ROAD_READ) != (1.2, 1, "mean")
    assert (own["temperature"], own["futures"], own["off_road_read"]) == (1.2, 1, "mean")
    subprocess.run(_probe(whole, "--temperature", "1.2", "--judge", "--world-steering", "1", "--futures", "1",
                          "--off-road-read", "mean", "--report", "plain.json"), check=True, capture_output=True,
                   timeout=600)
    with open(whole / "plain.json") as f:
        plain = json.load(f)
    assert (plain["world_steering"], plain["temperature"], plain["futures"], plain["off_road_read"]) \
        == ([1.0, 0.0], 1.2, 1, "mean")
    assert plain["per_track"]["dream"] != judged["per_track"]["dream"]

    # Killed once the first drives are kept, then run again: the same report.
    killed = tmp_path / "killed"
    process = subprocess.Popen(_probe(killed, "--workers", "2"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    end = time.time() + 300
    while not list(killed.glob("real/*.json")):
        assert time.time() < end and process.poll() is None, "no drive kept before the probe ended"
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    kept = len(list((killed / "real").glob("*.json")))
    assert 1 <= kept < 6
    resumed = subprocess.run(_probe(killed), check=True, capture_output=True, text=True, timeout=600)
    assert resumed.stdout.count("on track") == 6
    assert _report(killed) == report


def test_a_bad_weight_file_is_refused_before_any_drive(tmp_path):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not weights")
    for flag, path in (("--world", bad), ("--world", tmp_path / "missing.safetensors"), ("--weights", bad)):
        run = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "1", "--out",
                              str(tmp_path / "out"), flag, str(path)], capture_output=True, text=True, timeout=120)
        assert run.returncode == 2, run.stderr
        assert f"error: {flag}: " in run.stderr, run.stderr
        assert "Traceback" not in run.stderr and not (tmp_path / "out" / "real").exists()


def test_several_futures_of_the_mean_dream_are_refused(tmp_path):
    run = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "1", "--out",
                          str(tmp_path / "out"), "--futures", "2"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "--futures above 1 needs --temperature" in run.stderr, run.stderr
    assert not (tmp_path / "out").exists()
    judge = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "1", "--out",
                            str(tmp_path / "out"), "--judge", "--temperature", "0"], capture_output=True, text=True,
                           timeout=120)
    assert judge.returncode == 2 and "--judge needs --temperature" in judge.stderr, judge.stderr
    other = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "1", "--out",
                            str(tmp_path / "out"), "--judge", "--temperature", "1", "--world",
                            fixture("texture_f32.safetensors")], capture_output=True, text=True, timeout=120)
    assert other.returncode == 2 and "error: --world: " in other.stderr and "Traceback" not in other.stderr
    assert not (tmp_path / "out").exists()


def test_real_drives_of_other_drivers_are_refused(tmp_path):
    """The real drives in ``--out`` are the drivers' of ``--weights``: another policy (or another
    built-in default) with the same folder is an error, not a report mixing two families' drives."""
    from safetensors.numpy import load_file, save_file
    from safetensors import safe_open

    default = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "weights", "default.safetensors")
    built_in = rank_real.drivers_fingerprint(drivesim.Model.load())
    assert built_in == rank_real.drivers_fingerprint(drivesim.Model.load(default))
    tensors = load_file(default)
    with safe_open(default, "np") as f:
        meta = f.metadata()
    tensors["policy.output.bias"] = tensors["policy.output.bias"] + np.float16(0.25)
    save_file(tensors, tmp_path / "other.safetensors", metadata=meta)
    other = rank_real.drivers_fingerprint(drivesim.Model.load(tmp_path / "other.safetensors"))
    assert other != built_in

    rank_real.check_drivers(str(tmp_path), built_in)
    rank_real.check_drivers(str(tmp_path), built_in)  # the same drivers: the folder is theirs
    with pytest.raises(ValueError, match="other drivers"):
        rank_real.check_drivers(str(tmp_path), other)
    run = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "1", "--out", str(tmp_path),
                          "--weights", str(tmp_path / "other.safetensors")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "holds the real drives of other drivers" in run.stderr, run.stderr
    assert not os.listdir(tmp_path / "real")

"""Where the car is when it is off the road (``python -m drivesim.carracing.rank_sight``): the
frames measured, the bins, and a rank run's real windows driven again flag for flag."""

import json
import subprocess
import sys

import numpy as np
import pytest

from drivesim.carracing import rank_sight

GRASS, ROAD = (102, 204, 102), (105, 105, 105)


def frame(*boxes):
    """A grass frame with road-grey boxes (rows, columns)."""
    f = np.zeros((80, 160, 3), np.uint8)
    f[:] = GRASS
    for rows, cols in boxes:
        f[rows, cols] = ROAD
    return f


def test_sight_leaves_the_car_out_and_reads_the_road_ahead():
    frames = np.stack([
        frame(),                                    # grass only
        frame((slice(60, 74), slice(74, 86))),      # grey in the car's box only (its sprite)
        frame((slice(0, 80), slice(0, 12))),        # road at the frame's left edge: in sight, not ahead
        frame((slice(40, 58), slice(85, 95))),      # road just ahead and to the right of the car
    ])
    in_sight, ahead = rank_sight.sight(frames)
    assert in_sight.tolist() == [False, False, True, True] and ahead.tolist() == [False, False, False, True]


def test_figures_bin_the_decisions():
    off = np.array([[0, 0, 1, 1], [0, 1, 1, 0]], float)
    seen = np.array([[1, 1, 1, 0], [1, 1, 0, 1]], float)
    ahead = np.array([[1, 0, 0, 0], [1, 1, 0, 0]], float)
    bins = rank_sight.figures(np.stack([off, seen, ahead]), 2)
    assert [b["decisions"] for b in bins] == [[1, 2], [3, 4]]
    assert bins[0]["off_road"] == 0.25 and bins[0]["in_sight"] == 1.0 and bins[0]["ahead"] == 0.75
    assert bins[0]["in_sight_where_off"] == 1.0 and bins[1]["in_sight_where_off"] == pytest.approx(1 / 3)
    assert rank_sight.figures(np.stack([np.zeros((1, 2)), np.ones((1, 2)), np.ones((1, 2))]), 2)[0][
        "in_sight_where_off"] is None


def test_since_leaving_counts_from_the_first_decision_off():
    off = np.array([[0, 1, 1, 0, 1], [1, 1, 1, 1, 0]], bool)
    assert rank_sight.since_leaving(off).tolist() == [[-1, 0, 1, -1, 0], [0, 1, 2, 3, -1]]


def test_sight_since_leaving_bins_past_the_first_decisions():
    """Only decisions from ``first`` on count, each in the bin of how long ago its car left; a car
    that left before ``first`` is counted from when it left."""
    off = np.array([[0, 1, 1, 1, 1, 1, 1, 0], [0, 0, 0, 0, 0, 1, 1, 1]], float)
    seen = np.array([[1, 1, 1, 1, 1, 0, 0, 1], [1, 1, 1, 1, 1, 1, 1, 0]], float)
    bins = rank_sight.sight_since_leaving(np.stack([off, seen, seen]), first=4)
    assert [b["since"] for b in bins] == [list(b) for b in rank_sight.SINCE_BINS]
    assert [rank_sight.since_label(*b) for b in rank_sight.SINCE_BINS] == ["0", "1-2", "3-5", "6-10", "11-"]
    # row 0 at decisions 4-6: 3, 4, 5 since leaving; row 1 at 5-7: 0, 1, 2
    assert [b["frames"] for b in bins] == [1, 2, 3, 0, 0]
    assert bins[0]["in_sight"] == 1.0 and bins[1]["in_sight"] == 0.5
    assert bins[2]["in_sight"] == pytest.approx(1 / 3) and bins[3]["in_sight"] is None


def test_the_head_on_real_states_steps_the_world_on_the_frames(model, clip):
    """The world's chance of each state a real window showed: the first frame's code with the
    start's hidden state, each next with the hidden state the codes before and their inputs made;
    the same figures whatever the simulator's batch (11 frames: not a multiple of it)."""
    from drivesim import Simulator

    frames = np.ascontiguousarray(np.concatenate([clip[0], clip[0][::-1]])[:11])
    actions = np.concatenate([clip[1], clip[1][::-1]])[:11].astype(np.float32)
    h = np.random.default_rng(3).uniform(-0.5, 0.5, model.hidden_dim).astype(np.float32)
    world = Simulator(model, batch=4)
    head = rank_sight.head_on_frames(world, frames, actions, h)
    assert head.shape == (11,) and np.all((head >= 0) & (head <= 1))
    one = Simulator(model, batch=1)
    z = np.concatenate([one.encode(frames[t:t + 1]) for t in range(2)])
    assert head[0] == one.reward(z[:1], h[None])[0, 1]
    _, h1 = one.transition(z[:1], h[None], actions[:1])
    assert head[1] == one.reward(z[1:2], h1)[0, 1]
    np.testing.assert_array_equal(rank_sight.head_on_frames(Simulator(model, batch=16), frames, actions, h), head)


def test_the_real_windows_are_the_rank_runs_again(tmp_path):
    """On a rank run's drives: the real windows rank_sight drives again leave the road where the
    rank run's windows did, decision for decision."""
    pytest.importorskip("Box2D")
    out = tmp_path / "rank"
    common = ["--seeds", "3", "--out", str(out), "--frames", "160", "--horizon", "4", "--starts", "2"]
    subprocess.run([sys.executable, "-m", "drivesim.carracing.rank", *common, "--family", "small", "--windows"],
                   check=True, capture_output=True, timeout=600)
    report = tmp_path / "sight.json"
    run = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank_sight", *common, "--drivers", "0,5",
                          "--every", "2", "--report", str(report)], check=True, capture_output=True, text=True,
                         timeout=600)
    assert "clone" in run.stdout and "bias +0.4" in run.stdout
    figures = json.loads(report.read_text())["drivers"]
    with open(out / "windows_4x2" / "small_1_3.json") as f:  # bias +0.4 is the small family's second
        kept = json.load(f)
    flags = np.array(kept["off"], float)
    for b, (a, e) in zip(figures["bias +0.4"]["real"], ((0, 2), (2, 4))):
        assert b["off_road"] == pytest.approx(flags[:, a:e].mean())
    for side in ("real", "dream"):
        for b in figures["clone"][side]:
            assert 0 <= b["off_road"] <= 1 and 0 <= b["in_sight"] <= 1 and 0 <= b["ahead"] <= 1
            assert (0 <= b["head_on_real"] <= 1) if side == "real" else "head_on_real" not in b
        # a horizon of 4 has no decision past the view's reach to count since leaving
        assert [b["frames"] for b in figures["bias +0.4"]["since_leaving"][side]] == [0] * len(rank_sight.SINCE_BINS)


def test_a_folder_without_the_rank_runs_drives_is_refused(tmp_path):
    run = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank_sight", "--seeds", "3", "--out",
                          str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "has no behaviour drive of track 3" in run.stderr and "Traceback" not in run.stderr
    bad = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank_sight", "--seeds", "3", "--out",
                          str(tmp_path), "--drivers", "0,99"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--drivers" in bad.stderr

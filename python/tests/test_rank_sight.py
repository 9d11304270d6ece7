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


def test_across_reads_where_the_road_is_beside_the_car():
    """The road's centre in the car's rows, in half-roads (+: the car left of it); the car's own
    sprite and road outside those rows do not count; too little road there is no road (NaN)."""
    half = rank_sight.HALF_ROAD_PX
    rows = rank_sight.CAR_ROWS
    def band(centre, width=30):
        lo = int(round(80 + centre - width / 2))
        return (rows, slice(lo, lo + width))
    frames = np.stack([
        frame(band(0)),                                  # the car on the road's centre
        frame(band(2 * half)),                           # the road two half-roads to the car's right
        frame(band(-2 * half)),                          # two to its left: the car right of the road
        frame((slice(60, 74), slice(74, 86))),           # grey in the car's box only
        frame((slice(0, 40), slice(0, 160))),            # road far ahead only
        frame(),
    ])
    place = rank_sight.across(frames)
    assert place[:3] == pytest.approx([0.0, 2.0, -2.0], abs=0.05)
    assert np.isnan(place[3:]).all()


def test_across_follows_the_car_on_a_real_track():
    """On a real track, the place read off the frame rises and falls with the car's distance from
    the env's centre line (+ left), and the road is never gone from beside a car within 1.5
    half-roads of it."""
    pytest.importorskip("Box2D")
    import gymnasium

    from drivesim.carracing import expert
    from drivesim.carracing.record import HALF_ROAD
    from drivesim.carracing.view import observe

    read, true = [], []
    for seed in (5, 7):
        env = gymnasium.make("CarRacing-v3")
        env.reset(seed=seed)
        line = expert.CentreLine(env.unwrapped.track)
        for t in range(200):  # straight on past the env's zoom, then weaving
            steer = 0.0 if t < 80 else (-0.1 if (t // 30) % 2 else 0.1)
            env.step(np.array([steer, 0.2 if t < 120 else 0.0, 0.0], np.float32))
            if t >= 70:
                pos = np.array(env.unwrapped.car.hull.position)
                i, _ = line.nearest(pos)
                true.append(float((pos - line.centre[i]) @ line.left[i]) / HALF_ROAD)
                read.append(float(rank_sight.across(observe(env)[None])[0]))
        env.close()
    read, true = np.array(read), np.array(true)
    near = np.abs(true) < 1.5
    assert not np.isnan(read[near]).any() and true[near].min() < -1.0
    assert np.corrcoef(read[near], true[near])[0, 1] > 0.75


def test_road_beside_counts_where_the_road_is_lost():
    """From ``first`` on: each decision in the bin of its place, its off-road figure, and whether
    the road is gone the next decision; and the share of decisions with the road gone."""
    nan = np.nan
    place = np.array([[0.0, 0.0, -1.4, nan, nan], [0.0, 1.1, 1.1, 1.1, 0.2]])
    off = np.array([[0, 0, 1, 1, 1], [0, 0, 0, 1, 0]], float)
    measured = np.stack([off, np.ones_like(off), np.ones_like(off), place])
    b = rank_sight.road_beside(measured, first=1)
    cells = {tuple(c["place"]): c for c in b["places"]}
    assert sum(c["decisions"] for c in b["places"]) == 5  # decisions 1-3 with a place and a next
    assert cells[(-1.5, -1.25)] == {"place": [-1.5, -1.25], "decisions": 1, "off_road": 1.0, "lost": 1.0}
    assert cells[(1.0, 1.25)]["decisions"] == 3 and cells[(1.0, 1.25)]["lost"] == 0.0
    assert cells[(1.0, 1.25)]["off_road"] == pytest.approx(1 / 3)
    assert cells[(-0.5, 0.5)]["decisions"] == 1 and cells[(-0.5, 0.5)]["lost"] == 0.0
    assert cells[(None, -1.5)] == {"place": [None, -1.5], "decisions": 0, "off_road": None, "lost": None}
    assert b["gone"] == 0.25 and b["off_road_where_gone"] == 1.0
    assert [rank_sight.place_label(*c["place"]) for c in b["places"]][:2] == ["<-1.5", "-1.5..-1.25"]


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
        # a horizon of 4 has no decision past the view's reach to count since leaving, nor a place
        assert [b["frames"] for b in figures["bias +0.4"]["since_leaving"][side]] == [0] * len(rank_sight.SINCE_BINS)
        assert [c["decisions"] for c in figures["bias +0.4"]["beside"][side]["places"]] == [0] * (len(rank_sight.PLACES) + 1)
    # The world's steering shaped (`--world-steering`) moves the world alone, and the report says how.
    shaped = tmp_path / "shaped.json"
    subprocess.run([sys.executable, "-m", "drivesim.carracing.rank_sight", *common, "--drivers", "0,5", "--every", "2",
                    "--world-steering", "3,0.5", "--report", str(shaped)], check=True, capture_output=True, timeout=600)
    both = json.loads(report.read_text()), json.loads(shaped.read_text())
    assert [b["world_steering"] for b in both] == [[1.0, 0.0], [3.0, 0.5]]
    real = [[{k: v for k, v in b.items() if k != "head_on_real"} for b in r["drivers"]["clone"]["real"]] for r in both]
    assert real[0] == real[1]  # the world's head on the real states steps its memory with the shaped steering too
    assert both[0]["drivers"]["clone"]["dream"] != both[1]["drivers"]["clone"]["dream"]


def test_a_folder_without_the_rank_runs_drives_is_refused(tmp_path):
    run = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank_sight", "--seeds", "3", "--out",
                          str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "has no behaviour drive of track 3" in run.stderr and "Traceback" not in run.stderr
    bad = subprocess.run([sys.executable, "-m", "drivesim.carracing.rank_sight", "--seeds", "3", "--out",
                          str(tmp_path), "--drivers", "0,99"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--drivers" in bad.stderr

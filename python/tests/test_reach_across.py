"""How far across the road the dream carries the car under a recording's own actions
(``python -m drivesim.carracing.reach_across``): the bands, the windows, real and dreamt frames
read at the same step, and the command end to end."""

import json

import numpy as np
import pytest

from drivesim import episodes
from drivesim.carracing import reach_across, rank_sight

GRASS, ROAD = (102, 204, 102), (105, 105, 105)
# Places that fall in each band in turn: centre, edge, far out, road gone (None).
CYCLE = (0.0, 1.2, 2.0, None)


def drawn(place, index):
    """A grass frame with a road band whose centre is ``place`` half-roads right of the car (None:
    no road), and ``index`` written in grey-free pixels of the top row so that each frame is its own."""
    f = np.zeros((80, 160, 3), np.uint8)
    f[:] = GRASS
    if place is not None:
        lo = int(round(80 + place * rank_sight.HALF_ROAD_PX - 15))
        f[rank_sight.CAR_ROWS, max(lo, 0):lo + 30] = ROAD
    f[0, :4, 0] = np.frombuffer(np.int32(index).tobytes(), np.uint8)
    return f


def recording(lengths, steering=0.3):
    frames = np.stack([drawn(CYCLE[t % len(CYCLE)], t) for t in range(sum(lengths))])
    actions = np.tile(np.float32([30.0, steering]), (len(frames), 1))
    return episodes.Episodes(frames, actions, np.cumsum([0, *lengths[:-1]]))


def index_of(frames):
    return np.frombuffer(np.ascontiguousarray(frames[:, 0, :4, 0]).tobytes(), np.int32).astype(np.float32)


class PerfectWorld:
    """Dreams the recording itself: each predicted code is the index of the real frame it stands
    for (found from the seeds), and a code's frame is that frame. Keeps the actions it was given.
    As a driver, it encodes a frame as its index too and steers by where the road is in it."""
    batch = 7

    def __init__(self, data):
        self.data, self.given = data, []

    def encode(self, frames):
        return index_of(frames)[:, None]

    def act(self, z, h):
        place = rank_sight.across(self.data.frames[z[:, 0].astype(int)])
        return np.stack([np.zeros(len(z)), np.nan_to_num(place) * 0.3 - 0.1], 1)

    def transition(self, z, h, action):
        return z, h + 1

    def set_sampling(self, temperature, seed):
        self.sampling = (temperature, seed)

    def rollout(self, seeds, actions):
        first = int(index_of(seeds)[0])
        self.given.append((first, actions.copy()))
        steps = len(actions) - (len(seeds) - 1)
        return np.arange(first + len(seeds), first + len(seeds) + steps, dtype=np.float32)[:, None]

    def generate(self, codes):
        return self.data.frames[codes[:, 0].astype(int)]


def test_bands_count_gone_edge_and_far():
    bands = reach_across.bands(np.array([0.0, 0.9, -1.0, 1.4, -1.5, 3.0, np.nan, np.nan]))
    assert bands == pytest.approx({"gone": 2 / 8, "edge": 2 / 8, "far": 2 / 8})


def test_the_clone_gain_is_a_line_through_the_places_near_the_road():
    places = np.array([-1.0, 0.0, 0.5, 1.2, 2.0, np.nan])
    line = reach_across.clone_gain(0.2 * places + 0.05, places)
    assert line["gain"] == pytest.approx(0.2) and line["offset"] == pytest.approx(0.05) and line["points"] == 4
    assert reach_across.clone_gain(np.zeros(3), np.array([0.5, 3.0, np.nan]))["gain"] is None


def test_windows_fit_the_seeds_and_the_last_step():
    length = reach_across.SEEDS + reach_across.STEPS[-1]
    starts = reach_across.window_starts([(0, length + 10), (length + 10, length + 15), (length + 15, 2 * length + 55)], 10)
    assert starts.tolist() == [0, 10, length + 15, length + 25, length + 35, length + 45, length + 55]


def test_a_world_that_dreams_the_recording_reads_as_the_real_frames():
    """Real and dreamt frames are read at the same step: a world that dreams the recording itself
    has the real figures to the digit, on places that change band every frame (one frame off and
    every band would differ)."""
    data = recording([60, 45])
    world = PerfectWorld(data)
    report = reach_across.reach(world, data, every=4)
    assert report["windows"] == len(reach_across.window_starts(data.bounds(), 4))
    assert report["dream"] == report["real"]
    k = reach_across.STEPS[0]  # fed-back step k shows frame start + SEEDS - 1 + k
    assert report["real"][str(k)] == reach_across.bands(rank_sight.across(np.stack(
        [data.frames[s + reach_across.SEEDS - 1 + k] for s in reach_across.window_starts(data.bounds(), 4)])))
    assert len({tuple(b.values()) for b in report["real"].values()}) > 1
    # The clone steers 0.3 a half-road from -0.1, on the real codes as on the dreamt ones.
    report = reach_across.reach(world, data, every=4, driver=PerfectWorld(data), memory_dim=3)
    assert report["clone"]["real"] == report["clone"]["dream"]
    assert report["clone"]["real"]["gain"] == pytest.approx(0.3) and report["clone"]["real"]["offset"] == pytest.approx(-0.1)
    assert report["clone"]["real"]["points"] == 2 * report["windows"]  # the steps at the centre and at the edge


def test_the_dream_is_steered_as_rank_steers_it_from_the_first_predicted_step():
    data = recording([50], steering=0.3)
    data.actions[:, 1] = np.linspace(-0.6, 0.6, len(data.actions))
    world = PerfectWorld(data)
    reach_across.reach(world, data, every=100, shaping=(2.0, 0.5), temperature=0.5, seed=11)
    first, given = world.given[0]
    recorded = data.actions[first:first + len(given)]
    seeds = reach_across.SEEDS - 1
    assert np.array_equal(given[:seeds], recorded[:seeds])
    expected = np.clip(2.0 * recorded[seeds:, 1] + 0.5 * (recorded[seeds:, 1] - recorded[seeds - 1:-1, 1]), -1, 1)
    assert given[seeds:, 1] == pytest.approx(expected) and np.array_equal(given[:, 0], recorded[:, 0])
    assert world.sampling == (0.5, 11)


def test_the_command_reports_the_built_in_worlds(tmp_path):
    path = tmp_path / "drives.safetensors.gz"
    episodes.write(str(path), recording([60, 50]))
    for judge in ([], ["--judge"]):
        report = tmp_path / "reach.json"
        assert reach_across.main(["--episodes", str(path), "--every", "20", "--report", str(report), *judge]) == 0
        figures = json.loads(report.read_text())
        assert figures["windows"] >= 1 and figures["judge"] == bool(judge)
        for side in ("real", "dream"):
            for step in map(str, reach_across.STEPS):
                assert set(figures[side][step]) == {"gone", "edge", "far"}
                assert 0 <= sum(figures[side][step].values()) <= 1
        # the drawn frames' places near the road are two (centre, edge); what the dream draws of them may not be
        assert np.isfinite(figures["clone"]["real"]["gain"]) and figures["clone"]["real"]["points"] > 0
        assert figures["clone"]["dream"]["gain"] is None or np.isfinite(figures["clone"]["dream"]["gain"])


def test_bad_input_is_refused_with_a_message(tmp_path, capsys):
    assert reach_across.main(["--episodes", str(tmp_path / "missing.safetensors.gz")]) == 1
    short = tmp_path / "short.safetensors.gz"
    episodes.write(str(short), recording([20]))
    assert reach_across.main(["--episodes", str(short)]) == 1
    assert "no episode holds a window" in capsys.readouterr().err
    drives = tmp_path / "drives.safetensors.gz"
    episodes.write(str(drives), recording([60]))
    assert reach_across.main(["--episodes", str(drives), "--report", str(tmp_path / "no" / "dir" / "r.json")]) == 1
    assert "r.json" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        reach_across.main(["--episodes", str(short), "--judge", "--temperature", "0"])
    with pytest.raises(SystemExit):
        reach_across.main(["--episodes", str(short), "--every", "0"])

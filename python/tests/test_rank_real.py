"""The rank probe's real windows (``rank --windows``, ``drivesim.carracing.rank_real``): the env
replayed to a start is the car the behaviour drive had there, and a window of the unchanged
driver is that drive's own stretch, reward for reward."""

import json
import subprocess
import sys

import numpy as np
import pytest

import drivesim
from drivesim.carracing import rank_dream, rank_real
from drivesim.carracing.family import FAMILY, SMALL, ChangedAgent, Driver


def test_a_window_of_the_unchanged_driver_is_its_drive_reward_for_reward():
    pytest.importorskip("Box2D")
    import gymnasium

    model = drivesim.Model.load()
    agent = ChangedAgent(FAMILY[0], seed=0, model=model)
    _, states, trace = rank_real.drive_real(agent, 3, 240, keep_states=True)
    assert trace["actions"].shape == (60, 3) and len(trace["rewards"]) == len(trace["off"]) == 60
    env = gymnasium.make("CarRacing-v3", max_episode_steps=240)
    for start, horizon in ((agent.warmup + 3, 10), (40, 20)):
        env.reset(seed=3)
        rank_real.replay(env, trace["actions"][:start], agent.frame_skip)
        agent.reset()
        rewards, off, actions = rank_real.drive_window(env, agent, states[start - agent.warmup][1], start, horizon)
        np.testing.assert_allclose(rewards, trace["rewards"][start:start + horizon], atol=1e-4)
        np.testing.assert_array_equal(off, trace["off"][start:start + horizon].astype(bool))
        np.testing.assert_allclose(np.array(actions)[:, 1], trace["actions"][start:start + horizon, 0], atol=1e-4)
    # Another driver from the same state drives elsewhere.
    biased = ChangedAgent(Driver("b", bias=0.6), seed=0, model=model)
    env.reset(seed=3)
    rank_real.replay(env, trace["actions"][:20], agent.frame_skip)
    rewards, _, _ = rank_real.drive_window(env, biased, states[20 - agent.warmup][1], 20, 20)
    assert not np.allclose(rewards, trace["rewards"][20:40], atol=1e-4)
    env.close()


def test_the_probe_with_windows_end_to_end(tmp_path):
    pytest.importorskip("Box2D")
    command = [sys.executable, "-m", "drivesim.carracing.rank", "--seeds", "3,4", "--out", str(tmp_path), "--family",
               "small", "--frames", "160", "--horizon", "4", "--starts", "2", "--windows"]
    run = subprocess.run(command, check=True, capture_output=True, text=True, timeout=600)
    assert "windows: Spearman" in run.stdout
    assert f"the real window's actions (open loop):\n{'driver':24}{4:>18}\n" in run.stdout
    report = json.loads((tmp_path / "rank.json").read_text())
    windows = report["windows"]
    assert [d["driver"]["name"] for d in windows["drivers"]] == [d.name for d in SMALL]
    for d in windows["drivers"]:
        assert np.isfinite([d["real"], d["dream"]]).all() and 0 <= d["real_off_road"] <= 1
    # The unchanged driver's windows are its behaviour drive's stretches.
    for t, seed in enumerate((3, 4)):
        with np.load(tmp_path / f"drive_{seed}.npz") as f:
            drive = {k: f[k] for k in f.files}
        decisions, _ = rank_dream.window_starts(drive, 2, 4)
        kept = np.mean([drive["rewards"][d:d + 4].sum() for d in decisions])
        assert windows["per_track"]["real"][0][t] == pytest.approx(kept, abs=1e-3)
    # Each decision's off-road share: the unchanged driver's is its drives' flags there.
    by_decision = windows["off_by_decision"]
    assert np.shape(by_decision["real"]) == np.shape(by_decision["dream"]) == np.shape(by_decision["open_loop"]) \
        == (len(SMALL), 4)
    assert all(0 <= x <= 1 for kind in by_decision.values() for row in kind for x in row)
    flags = []
    for seed in (3, 4):
        with np.load(tmp_path / f"drive_{seed}.npz") as f:
            drive = {k: f[k] for k in f.files}
        decisions, at = rank_dream.window_starts(drive, 2, 4)
        flags += [drive["off"][d:d + 4] for d in decisions]
        # ... and the inputs its windows keep (for the open loop) are the drive's own.
        kept = json.loads((tmp_path / "windows_4x2" / f"small_0_{seed}.json").read_text())["actions"]
        np.testing.assert_allclose(kept, [np.stack([drive["speed"][t:t + 4], drive["steer"][t:t + 4]], 1) for t in at],
                                   atol=1e-3)
    np.testing.assert_allclose(by_decision["real"][0], np.mean(flags, 0))
    unchanged = windows["leaving"]["drivers"][0]  # ... and whether it leaves the road in them
    assert unchanged["real"]["leaves"] == pytest.approx(np.mean([np.any(f) for f in flags]))
    assert "leaving the road and coming back" in run.stdout
    # A behaviour drive kept without its actions (an older run) is driven again.
    with np.load(tmp_path / "drive_3.npz") as f:
        old = {k: f[k] for k in f.files if k not in ("actions", "rewards", "off")}
    np.savez(tmp_path / "drive_3.npz", **old)
    subprocess.run(command, check=True, capture_output=True, timeout=600)
    with np.load(tmp_path / "drive_3.npz") as f:
        assert "actions" in f.files
    assert json.loads((tmp_path / "rank.json").read_text())["windows"] == windows
    # A window kept without its flags and inputs (an older run) is driven again, to the same figures.
    path = tmp_path / "windows_4x2" / "small_1_3.json"
    old = json.loads(path.read_text())
    path.write_text(json.dumps({k: v for k, v in old.items() if k not in ("off", "actions")}))
    subprocess.run(command, check=True, capture_output=True, timeout=600)
    assert json.loads(path.read_text()) == old

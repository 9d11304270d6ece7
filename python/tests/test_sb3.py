"""drivesim.carracing.sb3: a stable-baselines3 policy as a real CarRacing agent (with a stand-in
policy: stable-baselines3 is not among the test requirements), and a clear error without it."""

import importlib.util

import numpy as np
import pytest

from drivesim.carracing.sb3 import PolicyAgent, main


class StandIn:
    """What the agent asks of a stable-baselines3 model: ``predict``."""

    def __init__(self):
        self.seen = []

    def predict(self, frame, deterministic):
        assert deterministic
        self.seen.append(frame)
        return np.array([1.7, 0.4, -0.2], np.float32), None


def test_the_policy_drives_after_the_warm_up_within_carracing_s_actions():
    policy = StandIn()
    agent = PolicyAgent(policy)
    frame = np.zeros((80, 160, 3), np.uint8)
    warm = [agent.act(frame, 10.0) for _ in range(agent.warmup)]
    assert all(a[0] == 0.0 for a in warm) and policy.seen == []
    assert np.array_equal(agent.act(frame, 10.0), np.array([1.0, 0.4, 0.0], np.float32))
    assert len(policy.seen) == 1
    with pytest.raises(ValueError, match="frame"):
        agent.act(np.zeros((80, 160), np.uint8), 10.0)
    agent.reset()
    assert agent.act(frame, 10.0)[0] == 0.0  # warming up again


@pytest.mark.skipif(importlib.util.find_spec("stable_baselines3") is not None, reason="stable-baselines3 is installed")
def test_without_stable_baselines3_the_error_says_what_to_install(tmp_path):
    with pytest.raises(ImportError, match="pip install stable-baselines3"):
        main(["score", "--policy", str(tmp_path / "p.zip"), "--seeds", "1"])


def test_score_refuses_frames_below_one(tmp_path):
    with pytest.raises(SystemExit):
        main(["score", "--policy", str(tmp_path / "p.zip"), "--seeds", "1", "--frames", "0"])

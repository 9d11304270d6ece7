"""drivesim.carracing.guard: the share of decisions where mpc's guard lets the candidates in."""

import numpy as np
import pytest

from drivesim import carracing
from drivesim.carracing import guard


def planned(agent, clip, decisions):
    """``agent`` deciding on the clip's first ``decisions`` views (no warm-up)."""
    frames, actions = clip
    agent.warmup = 0
    for f, a in zip(frames[:decisions], actions[:decisions]):
        agent.act(f, float(a[0]))
    return agent


def test_the_figure_is_the_one_the_guard_compares(clip):
    first = planned(carracing.make_agent("mpc", guard=1.0), clip, 1).chance
    assert 0.0 <= first <= 1.0
    # A guard just above the figure keeps the policy's action; at the figure the candidates weigh in.
    assert planned(carracing.make_agent("mpc", guard=min(1.0, first + 1e-6)), clip, 1).guarded == 1
    assert planned(carracing.make_agent("mpc", guard=first), clip, 1).guarded == 0


def test_the_figures_of_a_drive_one_a_planned_decision_and_the_shares(capsys):
    pytest.importorskip("Box2D")
    chances = guard.figures((None, 6000, 100))  # 25 decisions, 12 of them the warm-up's
    assert len(chances) == 13 and all(0.0 <= c <= 1.0 for c in chances)
    assert guard.main(["--seeds", "6000", "--frames", "100", "--guards", "0,1", "--rate", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "13 planned decisions on 1 tracks" in out
    assert "guard 0: the candidates weigh in at 100.00 %" in out
    assert f"at 50 % of the decisions: {np.median(chances):.4f}" in out


def test_guard_for_a_share():
    chances = np.arange(100) / 100.0
    assert guard.guard_for(chances, 0.1) == pytest.approx(0.891)
    assert np.mean(chances >= guard.guard_for(chances, 0.25)) == pytest.approx(0.25, abs=0.01)


@pytest.mark.parametrize("bad", [["--guards", "0.1,x"], ["--guards", "2"], ["--rate", "0"], ["--rate", "1"],
                                 ["--workers", "0"]])
def test_bad_options_are_refused(bad, capsys):
    with pytest.raises(SystemExit) as e:
        guard.main(["--seeds", "6000", *bad])
    assert e.value.code == 2 and "error" in capsys.readouterr().err

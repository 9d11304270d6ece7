"""drivesim.carracing.failures: the cloned driver changed, recorded as episodes with rewards (needs the
drivesim package and CarRacing: skipped without them)."""

import dataclasses

import numpy as np
import pytest

from drivesim import episodes

pytest.importorskip("Box2D")
from drivesim.carracing import failures  # noqa: E402 (after the skip: it needs Box2D)


def test_the_training_families_are_not_the_probes():
    from drivesim.carracing.family import FAMILY

    def changes(d):
        return tuple(v for k, v in dataclasses.asdict(d).items() if k != "name")

    probe = {changes(d) for d in FAMILY[1:]}
    for family in failures.FAMILIES.values():  # a driver may be in two families (more drives of it)
        mine = [changes(d) for d in family() if d.name != "clone"]
        assert mine and len(set(mine)) == len(mine) and not probe & set(mine)


def test_drives_recorded_and_resumed(tmp_path, capsys):
    out, kept = tmp_path / "failures.safetensors.gz", tmp_path / "drives"
    args = ["--tracks", "5,6", "--per-track", "2", "--frames", "120", "--dir", str(kept), "--out", str(out),
            "--workers", "1"]
    assert failures.main(args) == 0
    data = episodes.read(out)
    assert len(data.episode_starts) == 4
    n = len(data.frames)
    assert n == 4 * (120 // 4 - 12)  # every decision after the warm-up, no track ended early
    assert data.frames.shape == (n, 80, 160, 3) and data.actions.shape == (n, 2)
    assert set(data.rewards) == set(episodes.REWARDS) and all(len(v) == n for v in data.rewards.values())
    assert np.all(np.abs(data.actions[:, 1]) <= 1.0)
    # Track 5 is driven by the family's first two drivers, track 6 by the next two.
    assert sorted(p.name for p in kept.iterdir()) == [f"{s}_{i}.safetensors.gz" for s, i in ((5, 0), (5, 1), (6, 2), (6, 3))]
    capsys.readouterr()
    assert failures.main(args) == 0  # run again: every drive kept, none driven
    assert capsys.readouterr().out.count("kept from an earlier run") == 4
    again = episodes.read(out)
    np.testing.assert_array_equal(again.frames, data.frames)
    np.testing.assert_array_equal(again.actions, data.actions)


def test_another_family_kept_apart(tmp_path):
    kept = tmp_path / "drives"
    args = ["--family", "fast", "--tracks", "5", "--per-track", "1", "--frames", "80", "--dir", str(kept),
            "--out", str(tmp_path / "fast.safetensors.gz"), "--workers", "1"]
    assert failures.main(args) == 0
    assert [p.name for p in kept.iterdir()] == ["5_fast_0.safetensors.gz"]
    assert episodes.metadata(kept / "5_fast_0.safetensors.gz")["driver"] == failures.fast_family()[0].name

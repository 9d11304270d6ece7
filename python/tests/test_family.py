"""The changed drivers (``drivesim.carracing.family``): each change applied to its own row, a delay,
seeded noise, holds, and the unchanged driver driving as the clone."""

import numpy as np

import drivesim
from drivesim.carracing import family


def test_changes_apply_each_drivers_change_to_its_own_row():
    drivers = [family.Driver("a", gain=2.0, bias=0.1), family.Driver("b", speed=0.5), family.Driver("c", bias=-5.0)]
    changes = family.Changes(drivers, [0, 1, 2])
    out = changes(np.array([[40.0, 0.3], [40.0, 0.3], [40.0, 0.3]], np.float32))
    np.testing.assert_allclose(out, [[40.0, 0.7], [20.0, 0.3], [40.0, -1.0]], rtol=1e-6)


def test_a_delay_applies_the_action_decided_that_many_decisions_before():
    changes = family.Changes([family.Driver("late", delay=2), family.Driver("now")], [0, 1])
    applied = [changes(np.array([[10.0 * t, 0.1 * t]] * 2, np.float32)) for t in range(1, 5)]
    # The first decision stands in for the ones before the drive.
    np.testing.assert_allclose([a[0, 1] for a in applied], [0.1, 0.1, 0.1, 0.2], rtol=1e-6)
    np.testing.assert_allclose([a[1, 1] for a in applied], [0.1, 0.2, 0.3, 0.4], rtol=1e-6)


def test_noise_is_seeded_per_row():
    def run(seeds):
        changes = family.Changes([family.Driver("n", noise=0.5)] * 2, seeds)
        return np.stack([changes(np.zeros((2, 2), np.float32)) for _ in range(5)])
    a, b = run([3, 4]), run([3, 4])
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[:, 0], a[:, 1])
    assert np.abs(a[..., 1]).max() <= 1.0


def test_holds_hold_a_constant_steering_now_and_then_and_leave_other_rows_alone():
    drivers = [family.Driver("h", holds=0.3), family.Driver("n", noise=0.5)]
    changes = family.Changes(drivers, [5, 6])
    policy = np.array([[40.0, 0.02], [40.0, 0.02]], np.float32)
    applied = np.stack([changes(policy) for _ in range(400)])
    held = applied[:, 0, 1] != np.float32(0.02)
    starts, ends = np.flatnonzero(np.diff(held.astype(int)) == 1) + 1, np.flatnonzero(np.diff(held.astype(int)) == -1) + 1
    assert len(starts) >= 8  # one every 12-38 decisions, each 2-8 long
    for s, e in zip(starts, ends[ends > starts[0]]):
        run = applied[s:e, 0, 1]
        assert 2 <= len(run) <= 8 and np.all(run == run[0]) and 0.05 <= abs(run[0]) <= 0.3
    assert len(set(np.sign(applied[held, 0, 1]))) == 2  # either way
    np.testing.assert_array_equal(applied[:, :, 0], 40.0)
    # The row without holds draws its noise as it would alone.
    alone = family.Changes([drivers[1]], [6])
    np.testing.assert_array_equal(applied[:, 1], np.stack([alone(policy[:1])[0] for _ in range(400)]))


def test_releases_take_the_hands_off_the_wheel_now_and_then():
    drivers = [family.Driver("r", release=12), family.Driver("r+h", release=12, holds=0.3)]
    changes = family.Changes(drivers, [7, 8])
    applied = np.stack([changes(np.array([[40.0, 0.02]] * 2, np.float32)) for _ in range(600)])
    released = applied[:, 0, 1] == 0.0
    edges = np.diff(np.concatenate([[0], released.astype(int), [0]]))
    lengths = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    assert len(lengths) >= 12 and lengths.min() >= family.RELEASE_SHORTEST and lengths.max() <= 12
    assert set(np.unique(applied[:, 0, 1])) == {np.float32(0.0), np.float32(0.02)}
    # With holds too, some of the row's holds are releases and some a constant steering.
    held = applied[:, 1, 1][applied[:, 1, 1] != np.float32(0.02)]
    assert np.any(held == 0.0) and np.any(np.abs(held) >= 0.05)


def test_the_unchanged_driver_drives_as_the_clone():
    from drivesim.carracing.agents import ClonedAgent

    model = drivesim.Model.load()
    clone, unchanged, biased = ClonedAgent(model, pace=None), family.ChangedAgent(family.FAMILY[0], 0, model), \
        family.ChangedAgent(family.Driver("b", bias=0.3), 0, model)
    rng = np.random.default_rng(0)
    steer_gap = []
    for _ in range(clone.warmup + 6):
        frame, speed = rng.integers(0, 256, (80, 160, 3), dtype=np.uint8), float(rng.uniform(10, 40))
        a = clone.act(frame, speed)
        np.testing.assert_array_equal(a, unchanged.act(frame, speed))
        steer_gap.append(biased.act(frame, speed)[0] - a[0])
    assert steer_gap[0] == 0 and max(steer_gap) > 0  # the warm-up drives straight, then the bias shows


def test_no_driver_of_the_check_family_is_one_of_another_family_s():
    from drivesim.carracing import failures

    def changes(driver):
        fields = ("gain", "bias", "speed", "noise", "delay", "holds", "release")
        return {(f, getattr(driver, f)) for f in fields if getattr(driver, f) != getattr(family.Driver("clone"), f)}

    others = [d for f in (family.FAMILY, family.HOLDS) for d in f]
    others += [d for make in failures.FAMILIES.values() for d in make()]
    used = {frozenset(changes(d)) for d in others}
    check = family.FAMILIES["check"]
    assert check[0] == family.FAMILY[0] and len(check) >= 16
    assert len({d.name for d in check}) == len(check)
    for driver in check[1:]:
        assert changes(driver) and frozenset(changes(driver)) not in used, driver.name

"""The bearings: the road still to drive told from driven road in the view, and the turns."""

import os

import numpy as np
import pytest

from drivesim import carracing
from drivesim.carracing import bearings
from drivesim.carracing.bearings import Bearings, Sight

GRASS, PLAIN = (102, 204, 102), 102


def view(tiles, columns=(60, 101), fresh_columns=None):
    """A view of grass with a road up ``columns``, 6-row tiles from the bottom; ``tiles`` says
    of each whether it is still to drive (drawn in the env's three shades by its index) or
    driven (plain). ``fresh_columns``: a second stretch of road still to drive, across the
    whole height, at these columns."""
    frame = np.empty((80, 160, 3), np.uint8)
    frame[:] = GRASS
    for i, fresh in enumerate(tiles):
        rows = slice(max(80 - 6 * (i + 1), 0), 80 - 6 * i)
        frame[rows, columns[0]:columns[1]] = PLAIN + ((0, 2, 5)[i % 3] if fresh else 0)
    if fresh_columns is not None:
        for i in range(14):
            frame[max(80 - 6 * (i + 1), 0):80 - 6 * i, fresh_columns[0]:fresh_columns[1]] = PLAIN + (0, 2, 5)[i % 3]
    return frame


def test_sight_tells_the_road_still_to_drive_from_driven_road():
    fresh = Sight(view([True] * 14))
    assert fresh.ahead >= bearings.ROAD_SEEN and 0.5 < fresh.fresh < 0.8 and fresh.side == 0.0
    driven = Sight(view([False] * 14))
    assert driven.fresh == 0.0 and driven.fresh_pixels == 0 and driven.fresh_at is None
    # Still to drive only far ahead, beyond the patch: driven ahead, but the view shows where.
    far = Sight(view([False] * 9 + [True] * 5))
    assert far.fresh == 0.0 and far.fresh_pixels > bearings.FRESH_SEEN and far.fresh_at[0] < bearings.AHEAD_ROWS[0]
    grass = Sight(view([]))
    assert grass.ahead == 0 and grass.fresh is None and grass.side == 0.0 and grass.fresh_at is None
    # The road off to the left of the car: it says where.
    left = Sight(view([True] * 14, columns=(0, 30)))
    assert left.ahead == 0 and left.side == -1.0 and left.fresh_at[1] < 30
    # Another road colour (the env's domain randomisation): the shades are told apart the same way.
    assert Sight(view([True] * 14) - 40).fresh == pytest.approx(fresh.fresh)


def test_the_drivers_action_passes_unchanged_while_road_lies_ahead():
    watch, action = Bearings(), np.float32([0.3, 0.5, 0.0])
    for _ in range(3 * bearings.LOST_RUN):
        assert watch.act(view([True] * 14), 40.0, action) is action
    # Driven road ahead, even with road still to drive in sight: the driver's (turning round on
    # driven road was tried and is not done).
    for _ in range(3 * bearings.LOST_RUN):
        assert watch.act(view([False] * 14, fresh_columns=(0, 20)), 40.0, action) is action
    # No road ahead for fewer than LOST_RUN decisions (a bend's edge, a moment on the grass).
    for _ in range(bearings.LOST_RUN - 1):
        assert watch.act(view([]), 40.0, action) is action
    assert watch.act(view([True] * 14), 40.0, action) is action and watch.turns == 0


def test_off_the_road_with_road_still_to_drive_in_sight_it_steers_for_it():
    watch, action = Bearings(), np.float32([0.3, 0.5, 0.0])
    lost = view([], fresh_columns=(0, 20))  # grass ahead, road still to drive on the left
    taken = [watch.act(lost, 40.0, action) for _ in range(bearings.LOST_RUN)]
    assert all(a is action for a in taken[:-1]) and watch.turns == 1
    steer, gas, brake = taken[-1]
    assert steer < -0.5 and gas == 0.0 and brake > 0  # toward it, slowing to TURN_SPEED
    assert watch.act(lost, 12.0, action)[1] > 0  # under TURN_SPEED: gas
    # That road ahead: the driver drives on.
    assert watch.act(view([True] * 14), 15.0, action) is action and watch.turn is None
    # Out of sight before it lies ahead: the driver too (the watch starts counting again).
    for _ in range(bearings.LOST_RUN):
        watch.act(lost, 15.0, action)
    assert watch.turns == 2 and watch.act(view([]), 15.0, action) is action


def test_a_car_that_lost_the_road_searches_toward_where_it_was():
    watch, action = Bearings(), np.float32([0.0, 0.6, 0.0])
    watch.act(view([True] * 14, columns=(0, 30)), 40.0, action)  # the last road seen: on the left
    lost = view([])
    taken = [watch.act(lost, 40.0, action) for _ in range(bearings.LOST_RUN)]
    assert all(a is action for a in taken[:-2]) and watch.turns == 1
    assert taken[-1][0] == 0.0 and taken[-1][2] > 0  # slowing first, the wheels straight
    searching = watch.act(lost, 12.0, action)
    assert searching[0] == -1.0 and searching[1] > 0  # full lock toward the road
    # It ends where road lies ahead, or after a full circle dead reckoned from the speed.
    assert watch.act(view([False] * 14), 15.0, action) is action and watch.turn is None
    watch.reset()
    for _ in range(bearings.LOST_RUN):
        watch.act(lost, 15.0, action)
    circle = bearings.SEARCH_TURN * bearings.TURN_RADIUS / (15.0 * bearings.DECISION_SECONDS)
    turning = [watch.act(lost, 15.0, action) is not action for _ in range(int(circle) + 2)]
    assert sum(turning) == pytest.approx(circle, abs=1.5) and not turning[-1]


def test_the_option():
    assert carracing.make_agent("cloned").bearings is not None
    assert carracing.make_agent("mpc", bearings=False).bearings is None
    for bad, error in ((2, ValueError), (0.5, ValueError), ("on", TypeError), (None, TypeError)):
        with pytest.raises(error, match="bearings"):
            carracing.make_agent("cloned", bearings=bad)


def test_the_env_draws_driven_tiles_plain():
    """What the watch relies on: gymnasium's CarRacing shades the tiles still to drive and
    draws those the car has touched in the plain road colour."""
    pytest.importorskip("Box2D")
    import gymnasium

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    env = gymnasium.make("CarRacing-v3")
    env.reset(seed=3)
    for _ in range(100):  # past the camera's zoom, driving up the first straight
        env.step(np.float32([0.0, 0.2, 0.0]))
    frame = carracing.observe(env)
    assert Sight(frame).fresh > bearings.FRESH
    # Under and behind the car (rows 66-80, beside its body): driven, plain.
    below = frame[66:, 62:74].reshape(-1, 3).astype(int)
    grey = below[(below.max(1) - below.min(1) <= 1) & (below[:, 0] > 60) & (below[:, 0] < 170)][:, 0]
    assert len(grey) > 20 and (grey == np.percentile(grey, 50)).mean() > 0.9
    env.close()

"""Keeping the lap's bearings: a driver that has lost the road steers for the road still to
drive, or turns until road lies ahead.

CarRacing draws the road's tiles in three shades until the car touches them (the env's road
colour plus 0, 2.55 or 5.1 per channel, by the tile's index) and every tile the car has touched
in the plain road colour: the view shows which road is still to drive. The models never
learnt that. After a spin, or a cut across the grass onto a stretch of the track beside it,
the clone drives the road it meets whichever way that runs, or on across the grass, and the lap
is lost (``docs/carracing.md``, "Keeping its bearings").

``Bearings`` watches the road just ahead of the car at every decision. Where for ``LOST_RUN``
decisions in a row no road lies just ahead (the car has left the road, in a spin or across the
grass), it takes over: where the view shows road still to drive, it steers for it at
``TURN_SPEED`` until that road lies ahead (at most ``SEEK`` decisions); where it shows none, it
slows and turns at full lock toward where the view last showed road until road lies ahead (at
most a full circle, dead reckoned from the speedometer). Then the driver drives on.

Otherwise the driver's own action passes unchanged: a drive where the watch never takes over
is the driver's own, bit for bit. Taking over on a car that drives road already driven (turning
round, or steering for road still to drive in sight) was tried and is not done: those laps are
lost where the track folds back on itself, and a turn there meets another stretch the wrong way
as often as the right one (docs/carracing.md, "Keeping its bearings").
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from .. import _checks
from .control import speed_control

#: The patch of the view just ahead of the car (rows, columns of the 80x160 view): the car's
#: nose is at row 62, column 80; the patch spans about 12 Box2D units ahead and 15 across.
AHEAD_ROWS, AHEAD_COLS = (30, 62), (60, 100)
#: Where the car sits in the view (row, column), for steering toward what the view shows.
CAR = (66.0, 80.0)
#: Road pixels in the patch (of 1,280) that are enough to judge the road ahead, and fewer than
#: which no road lies ahead; road still to drive in the whole view enough to steer for.
ROAD_SEEN, NO_ROAD, FRESH_SEEN = 300, 20, 150
#: The share of the road ahead in a lighter shade than the plain colour over which it is road
#: still to drive (that shows about 0.6-0.75: two tiles in three are lighter; driven road 0).
FRESH = 0.3
#: Decisions in a row with no road ahead before the watch takes over.
LOST_RUN = 8
#: The speed of the turns (units/s), and the radius the car turns at full lock there (Box2D
#: units: pi radians in 20 decisions at 15-16 units/s, measured on the env).
TURN_SPEED, TURN_RADIUS = 15.0, 8.1
#: The most a search for the road turns (radians, dead reckoned).
SEARCH_TURN = 2.0 * math.pi
#: The most decisions spent steering for road still to drive that the view shows.
SEEK = 40
#: Seconds a decision lasts (4 frames at 50 Hz).
DECISION_SECONDS = 0.08


class Sight:
    """What a checked view ``(80, 160, 3)`` uint8 shows of the road: ``ahead``, the road pixels
    just ahead of the car (``AHEAD_ROWS``, ``AHEAD_COLS``); ``fresh``, the share of them in a
    lighter shade than the plain colour (None where ``ahead < ROAD_SEEN``); ``side``, where the
    view's road lies (-1 left of the car, +1 right, 0 none); ``fresh_pixels`` and ``fresh_at``,
    the road still to drive in the whole view and its centre ``(row, column)``."""

    def __init__(self, frame: np.ndarray):
        view = frame[: AHEAD_ROWS[1]].astype(np.int16)
        # Road is grey: the channels agree (the grass's green and the kerbs' red do not; a pixel
        # blended with them at the road's edge neither). Stricter than ``road.road_mask``, whose
        # edge blends would read as a lighter shade.
        grey = (view.max(axis=-1) - view.min(axis=-1) <= 1) & (view[..., 0] > 60) & (view[..., 0] < 170)
        values = view[..., 0]
        # The plain colour is the darkest of the road's three shades; a kerb's white blended in
        # is lighter than all three.
        plain = np.percentile(values[grey], 10) if grey.any() else 0.0
        road = grey & (values <= plain + 8)
        lighter = road & (values >= plain + 2)
        r0, c0, c1 = AHEAD_ROWS[0], AHEAD_COLS[0], AHEAD_COLS[1]
        self.ahead = int(road[r0:, c0:c1].sum())
        self.fresh = float(lighter[r0:, c0:c1].sum() / self.ahead) if self.ahead >= ROAD_SEEN else None
        columns = np.nonzero(road)[1]
        self.side = float(np.sign(columns.mean() - CAR[1])) if len(columns) else 0.0
        rows, columns = np.nonzero(lighter)
        self.fresh_pixels = len(rows)
        self.fresh_at = (float(rows.mean()), float(columns.mean())) if len(rows) else None


def steering_toward(at: tuple) -> float:
    """The steering (in [-1, 1]) toward a point ``(row, column)`` of the view: its bearing from
    the car, full lock from 0.6 radians."""
    bearing = math.atan2(at[1] - CAR[1], max(CAR[0] - at[0], 1.0))
    return float(np.clip(bearing / 0.6, -1.0, 1.0))


def bearings_option(bearings) -> Optional["Bearings"]:
    """An agent's ``bearings`` option checked (True or False, 1 or 0; TypeError for what is not
    a number, ValueError for another number): a ``Bearings`` for its drives, or None."""
    return Bearings() if _checks.flag("bearings", bearings) else None


class Bearings:
    """The module's watch for one drive: ``reset()`` at every episode, ``act(frame, speed,
    action)`` at every decision with the driver's action; returns the action to apply.
    ``turns`` counts the times it took over."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.lost_run = 0
        self.turn: Optional[list] = None  # [kind, direction, decisions or radians left]
        self.side = 1.0  # where the view last showed road: -1 left, +1 right
        self.turns = 0

    def act(self, frame: np.ndarray, speed: float, action: np.ndarray) -> np.ndarray:
        sight = Sight(frame)
        self.side = sight.side or self.side
        if self.turn is None:
            self.lost_run = self.lost_run + 1 if sight.ahead < NO_ROAD else 0
            if self.lost_run < LOST_RUN:
                return action
            seek = sight.fresh_pixels >= FRESH_SEEN
            self.turn = ["seek", 0.0, SEEK] if seek else ["search", self.side, SEARCH_TURN]
            self.turns += 1
            self.lost_run = 0
        return self.turning(sight, speed, action)

    def turning(self, sight: Sight, speed: float, action: np.ndarray) -> np.ndarray:
        kind, direction, left = self.turn
        fresh_ahead = sight.fresh is not None and sight.fresh > FRESH
        found = sight.fresh_at is not None if kind == "seek" else sight.ahead >= ROAD_SEEN
        if left <= 0.0 or fresh_ahead or (kind == "search" and found) or (kind == "seek" and not found):
            self.turn = None
            return action
        if kind == "seek":
            self.turn[2] -= 1
            steer = steering_toward(sight.fresh_at)
        elif speed > TURN_SPEED + 5.0:  # slow first: at full lock at speed the car spins
            steer = 0.0
        else:
            self.turn[2] -= speed * DECISION_SECONDS / TURN_RADIUS
            steer = direction
        gas, brake = speed_control(speed, TURN_SPEED)
        return np.array([steer, gas, brake], np.float32)

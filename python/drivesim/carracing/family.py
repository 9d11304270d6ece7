"""The changed drivers: the cloned policy with one or two things changed (steering gain, a
steering bias, the target speed scaled, seeded steering noise, a delay, holds of a constant
steering, the hands off the wheel now and then), the same code for a real drive
(``ChangedAgent``) and for a batch of drives in the dream (``Changes``, a row per drive). The
rank probe's families are here (``drivesim.carracing.rank``); the failure data's are its own
(``drivesim.carracing.failures``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .agents import ClonedAgent
from .control import SPEED_MAX


@dataclass(frozen=True)
class Driver:
    """The cloned policy with its action changed: steering ``gain * steer + bias + noise`` (noise
    normal with sd ``noise``, clipped to [-1, 1]), the target speed times ``speed``, every
    action applied ``delay`` decisions late, and (``holds`` > 0) now and then a hold: a constant
    steering of 0.05 to ``holds`` either way for ``HOLD_DECISIONS``, every ``HOLD_EVERY``
    decisions or so, whatever the road does (what steering does at the policy's pace); and
    (``release`` > 0) now and then the hands off the wheel: steering 0 for ``RELEASE_SHORTEST`` to
    ``release`` decisions, as often as the holds (what the road does when nobody steers: it
    bends away)."""

    name: str
    gain: float = 1.0
    bias: float = 0.0
    speed: float = 1.0
    noise: float = 0.0
    delay: int = 0
    holds: float = 0.0
    release: int = 0


#: A hold's length and the decisions between holds (drawn uniformly; 12.5 decisions a second).
HOLD_DECISIONS, HOLD_EVERY = (2, 8), (12, 38)
#: The shortest release of the wheel, in decisions (its longest is the driver's ``release``).
RELEASE_SHORTEST = 4


FAMILY = [
    Driver("clone"),
    Driver("gain 0.5", gain=0.5), Driver("gain 2", gain=2.0),
    Driver("bias -0.2", bias=-0.2), Driver("bias +0.2", bias=0.2), Driver("bias +0.4", bias=0.4),
    Driver("speed 0.6", speed=0.6), Driver("speed 1.3", speed=1.3),
    Driver("noise 0.3", noise=0.3), Driver("noise 0.7", noise=0.7),
    Driver("delay 2", delay=2), Driver("delay 4", delay=4),
    Driver("gain 1.5, speed 1.2", gain=1.5, speed=1.2),
    Driver("bias +0.2, noise 0.3", bias=0.2, noise=0.3),
    Driver("delay 2, speed 1.2", delay=2, speed=1.2),
    Driver("gain 0.5, bias -0.2", gain=0.5, bias=-0.2),
    Driver("noise 1, speed 0.8", noise=1.0, speed=0.8),
]
#: A family small enough for a test: the clone and two drivers it must rank apart.
SMALL = [FAMILY[0], FAMILY[5], FAMILY[6]]
#: The clone's own pace with a constant steering from the start, whatever the road does: at 55
#: units/s the real car leaves the road within about 7 decisions. With ``--windows --horizon 20``
#: it measures whether the dream carries the car off the road when steering alone would; the last,
#: hands off the wheel from the start, whether it does when the road bends and nobody steers.
HOLDS = [FAMILY[0]] + [Driver(f"hold {b:+.2f}", gain=0.0, bias=b) for b in (-0.5, -0.25, -0.1, 0.1, 0.25, 0.5)] \
    + [Driver("hands off", gain=0.0)]
#: A second family, for checking a world tuned on ``FAMILY``: none of its drivers is one of the
#: probe's families or of the failure data's (``failures``); a hold and a release of the wheel are
#: among them, and the same spread of quality.
CHECK = [
    FAMILY[0],
    Driver("gain 0.7", gain=0.7), Driver("gain 2.2", gain=2.2),
    Driver("bias +0.15", bias=0.15), Driver("bias +0.25", bias=0.25), Driver("bias -0.25", bias=-0.25),
    Driver("speed 0.85", speed=0.85), Driver("speed 1.1", speed=1.1),
    Driver("noise 0.15", noise=0.15), Driver("noise 0.6", noise=0.6),
    Driver("holds 0.4", holds=0.4), Driver("release 7", release=7),
    Driver("gain 0.7, bias +0.1", gain=0.7, bias=0.1),
    Driver("noise 0.4, delay 1", noise=0.4, delay=1),
    Driver("speed 1.2, bias -0.1", speed=1.2, bias=-0.1),
    Driver("gain 1.8, speed 0.8", gain=1.8, speed=0.8),
    Driver("delay 2, noise 0.2", delay=2, noise=0.2),
]
#: Steady pulls either side of where the clone can no longer hold them (the real car's share off
#: the road rises from about 0.1 to 0.7 between +0.2 and +0.25): the curve that reads a dreamt share
#: as the pull that leaves the real road as often (``rank_figures.equivalent_pulls``).
CLIFF = [FAMILY[0]] + [Driver(f"bias {b:+.3g}", bias=b) for b in (-0.25, -0.2, -0.15, 0.15, 0.175, 0.2, 0.225, 0.25)]
#: The clone at target speeds from slower to far faster than it drives (``FAMILY`` goes to 1.3):
#: does the dream take the car off the road where speed alone does (issue 58: "at every speed")?
SPEEDS = [FAMILY[0]] + [Driver(f"speed {s:g}", speed=s) for s in (0.8, 1.15, 1.3, 1.45, 1.6, 1.8)]
FAMILIES = {"all": FAMILY, "small": SMALL, "holds": HOLDS, "check": CHECK, "cliff": CLIFF, "speeds": SPEEDS}


class Changes:
    """The drivers' changes applied to a batch of policy actions, one row per drive (each row's
    driver, noise drawn from its own generator, delays kept per row): the same code for the real
    drives (one row) and the dream's (a row per driver and start)."""

    def __init__(self, drivers: list, seeds: list):
        self.gain, self.bias, self.speed, self.noise = (
            np.array([getattr(d, f) for d in drivers], np.float32) for f in ("gain", "bias", "speed", "noise"))
        self.delay = np.array([d.delay for d in drivers], np.int64)
        self.holds = np.array([d.holds for d in drivers], np.float32)
        self.release = np.array([d.release for d in drivers], np.int64)
        self.rngs = [np.random.default_rng(s) for s in seeds]
        # Each row's hold: its steering, the decisions it has left, and the decisions until the next.
        self.hold_steer, self.hold_left = np.zeros(len(drivers), np.float32), np.zeros(len(drivers), np.int64)
        self.until_hold = np.array([rng.integers(*HOLD_EVERY, endpoint=True) if h > 0 or r > 0 else 0
                                    for rng, h, r in zip(self.rngs, self.holds, self.release)])
        self.queue = None  # (max delay + 1, N, 2): the actions decided, newest last

    def __call__(self, actions: np.ndarray) -> np.ndarray:
        """``(N, 2)`` policy actions (target speed, steering) to the actions applied."""
        noise = np.array([rng.standard_normal() for rng in self.rngs], np.float32) * self.noise
        steer = np.clip(self.gain * actions[:, 1] + self.bias + noise, -1.0, 1.0)
        steer = np.where(self.hold_tick(), self.hold_steer, steer)
        target = np.clip(self.speed * actions[:, 0], 0.0, SPEED_MAX)
        decided = np.stack([target, steer], 1).astype(np.float32)
        if self.queue is None:  # a drive starts with its first decision already in the past
            self.queue = np.repeat(decided[None], self.delay.max() + 1, 0)
        self.queue = np.concatenate([self.queue[1:], decided[None]])
        return self.queue[-1 - self.delay, np.arange(len(self.delay))]

    def hold_tick(self) -> np.ndarray:
        """One decision of the rows' holds: which rows hold their steering now (a hold drawn where
        one is due, a release of the wheel where the row has releases (half of them where it has
        holds too); only rows with holds or releases draw, so the others' noise stays as it was)."""
        for i in np.flatnonzero((self.holds > 0) | (self.release > 0)):
            if self.hold_left[i] == 0:
                self.until_hold[i] -= 1
                if self.until_hold[i] <= 0:
                    rng = self.rngs[i]
                    if self.release[i] > 0 and (self.holds[i] == 0 or rng.random() < 0.5):
                        self.hold_steer[i] = 0.0
                        longest = max(RELEASE_SHORTEST, self.release[i])
                        self.hold_left[i] = rng.integers(RELEASE_SHORTEST, longest, endpoint=True)
                    else:
                        self.hold_steer[i] = rng.choice([-1.0, 1.0]) * rng.uniform(0.05, self.holds[i])
                        self.hold_left[i] = rng.integers(*HOLD_DECISIONS, endpoint=True)
                    self.until_hold[i] = rng.integers(*HOLD_EVERY, endpoint=True)
        holding = self.hold_left > 0
        self.hold_left[holding] -= 1
        return holding


class ChangedAgent(ClonedAgent):
    """``ClonedAgent`` whose every decision passes through a driver's ``Changes``."""

    def __init__(self, driver: Driver, seed: int, model=None, threads: int = 1):
        self.driver, self.seed = driver, seed
        # The family changes the policy's own drive: no racing pace, no turns of the bearings.
        super().__init__(model, threads, pace=None, bearings=False)

    def reset(self) -> None:
        super().reset()
        self.changes = Changes([self.driver], [self.seed])

    def decide(self, z: np.ndarray) -> tuple:
        target, steer = self.changes(self.sim.act(z, self.h)[None])[0]
        return float(target), float(steer)

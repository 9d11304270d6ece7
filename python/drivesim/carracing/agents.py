"""Agents that drive gymnasium's CarRacing from the models' view and the speedometer alone.

``MPCAgent`` ("mpc", ``mpc.py``) plans in the simulator: MPPI over the policy's own plan and
perturbed copies of it, in the dream, scored by the model's learned reward and value heads.
``RoadMPCAgent`` ("mpc-road", ``road_mpc.py``), the first planner, searches steering ramps on a
grid scored by the hand-fitted ``RoadCost``.

``ClonedAgent`` ("cloned") drives as its teacher did: behavioural cloning (the default's policy:
the privileged expert and three DAgger rounds, ``drivesim.carracing.dagger``), the policy in the weight
file (``Simulator.act``, trained by ``train policy``) reading the code of the frame
seen now and the transition's hidden state stepped along the drive, and giving the steering and
the speed to drive at (through the same speed controller).

``DreamtAgent`` ("dreamt", ``dreamt.py``) drives with a driver learnt inside the dream: a
controller of ``python -m drivesim dream-train`` read from ``controller=FILE``, or without one
the weight file's policy head, which ``weights/tool train driver`` learnt in the dream
(``traction=True``: with the clone's traction control under it).

``ReactiveAgent`` ("reactive") is the baseline without the models: the proportional steering
and the speed controller alone.

Every agent checks its options when it is made and its inputs at every ``act``, the warm-up
decisions included: ``frame`` must be the models' view, a uint8 array ``(80, 160, 3)``
(ValueError otherwise), and ``speed`` the speedometer, a finite number from 0 to
``SPEED_MAX`` (TypeError for what is not a number, ValueError otherwise). Actions are finite.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .. import _checks
from .._drivesim import Model
from ..road import measure
from .control import (  # noqa: F401 (re-exported: the agents' building blocks)
    FRAME_SHAPE,
    SPEED_MAX,
    ModelAgent,
    check_inputs,
    proportional_steering,
    speed_after,
    speed_control,
    target_speed,
    warmup_action,
)
from .cloned import ClonedAgent
from .dreamt import DreamtAgent, driven_model
from .mpc import MPCAgent
from .road_mpc import RoadMPCAgent


class RandomAgent:
    """Random actions, as ``env.action_space.sample()`` draws them (steer in [-1, 1], gas and
    brake in [0, 1]), from a generator seeded at every ``reset()``: the floor of the table."""

    frame_skip = 4

    def __init__(self, seed: int = 0):
        self.seed = _checks.integer("seed", seed, 0)
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        check_inputs(frame, speed)
        return np.array([self.rng.uniform(-1, 1), self.rng.uniform(0, 1), self.rng.uniform(0, 1)], np.float32)


class ReactiveAgent:
    """A baseline without the models: proportional steering on the road measured in the real
    frame (``road.measure``) and the same speed target and controller as ``MPCAgent``. What the
    dream adds to driving is ``MPCAgent``'s score less this one's."""

    frame_skip = 4
    warmup = 12

    def __init__(self, max_speed: float = 52.0):
        self.max_speed = _checks.number("max_speed", max_speed, 0.0, SPEED_MAX, above=True)
        self.reset()

    def reset(self) -> None:
        self.decisions = 0

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        frame, speed = check_inputs(frame, speed)
        warming_up = warmup_action(self, speed)
        if warming_up is not None:
            return warming_up
        road = measure(frame[None])[0]
        gas, brake = speed_control(speed, target_speed(road, self.max_speed, frame.shape[1] / 2))
        return np.array([proportional_steering(road), gas, brake], np.float32)


AGENTS = {
    "mpc": MPCAgent,
    "mpc-road": RoadMPCAgent,
    "cloned": ClonedAgent,
    "dreamt": DreamtAgent,
    "reactive": ReactiveAgent,
    "random": RandomAgent,
}


def make_agent(name: str, weights: Optional[str] = None, threads: int = 1, **options):
    """An agent by name: ``"mpc"`` (planning in the simulator with the learned heads),
    ``"mpc-road"`` (the grid planner with the hand-fitted road cost), ``"cloned"`` (the policy in
    the weight file), ``"dreamt"`` (a driver learnt in the dream: without options the built-in one, learnt in
    the default's dream; ``driver=FILE``, a driver file for ``weights``' world; the weight file's
    policy that ``weights/tool train driver`` wrote; or ``controller=FILE`` of ``dream-train``), or the
    baselines without the models, ``"reactive"`` and ``"random"``.
    ``weights``: a weight file (the built-in default model when None; for ``"mpc-road"``,
    another model also needs ``cost=RoadCost...``). ``options`` are the agent's (``MPCAgent``
    and ``RoadMPCAgent`` say which they take); ValueError or TypeError for an option out of
    range or of the wrong kind."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}: one of {', '.join(sorted(AGENTS))}")
    if name not in ("mpc", "mpc-road", "cloned", "dreamt"):
        return AGENTS[name](**options)
    if name == "dreamt":
        model = driven_model(weights, options.pop("driver", None), options.get("controller"))
    else:
        model = Model.load(weights)
    return AGENTS[name](model=model, threads=threads, **options)

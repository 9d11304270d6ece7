"""The cloned driver: the model's policy (behavioural cloning, then DAgger) drives; what the
drivers that step the transition on the view's codes share (``dreamt.DreamtAgent``,
``family.ChangedAgent``)."""

from __future__ import annotations

from typing import Optional

import numpy as np

from .. import _checks
from .._drivesim import Model, Simulator
from .bearings import bearings_option
from .control import ModelAgent, Wheelspin, grip_speed, speed_after, speed_control


#: ``ClonedAgent``'s default ``pace``: the top speed at the pace head's speed (units/s). Chosen
#: on tuning tracks 5000-5319 with the grip envelope and the traction control (80: 917.7, none
#: under 800; 72: 914.3; 90: 917.2, one spin), docs/carracing.md.
PACE = 80.0
#: How far below the top of its trained speed range the policy's speed counts as at the top.
AT_THE_TOP = 1.0
#: ``ClonedAgent``'s default ``grip``: the share of the expert's grip envelope
#: (``control.grip_speed``) that racing pace stays under where it drives faster than the policy.
GRIP = 1.0


def racing_pace(sim: Simulator, z: np.ndarray, h: np.ndarray, target: float, top: float, cap: float,
                steer: float = 0.0, grip: Optional[float] = None) -> float:
    """The speed to drive at for the policy's ``target`` and ``steer`` at the state ``(z, h)``:
    the pace head's (``sim.pace``) where ``target`` is at ``top``, the top of the policy's trained
    speed range (within ``AT_THE_TOP``), the lower of the two below it, at most ``cap``; and where
    that is above ``target``, at most ``grip`` times the expert's grip envelope at ``steer``
    (None: no envelope)."""
    pace = float(sim.pace(z, h)[0])
    paced = min(pace if target >= top - AT_THE_TOP else min(pace, target), cap)
    if grip is not None and paced > target:
        paced = min(paced, grip * grip_speed(steer))
    return paced


def top_speed(model: Model) -> float:
    """The top of the policy's trained speed range (``drivesim.actions``; inf without it)."""
    return model.actions[0]["max"] if model.actions else np.inf


def pace_option(model: Model, pace: Optional[float]) -> Optional[float]:
    """An agent's ``pace`` option checked (a speed above 0, or None), and None where ``model``
    has no pace head: such a model drives at its policy's speed."""
    pace = None if pace is None else _checks.number("pace", pace, 0.0, above=True)
    return pace if model.pace_width is not None else None


def grip_option(grip: Optional[float]) -> Optional[float]:
    """An agent's ``grip`` option checked: a share of the grip envelope from 0.5 to 2, or None."""
    return None if grip is None else _checks.number("grip", grip, 0.5, 2.0)


def traction_option(traction, pace: Optional[float]) -> Optional[Wheelspin]:
    """An agent's ``traction`` option checked (True or False, 1 or 0): its traction control
    (``control.Wheelspin``) at racing pace, None without it or without ``pace``."""
    return Wheelspin() if _checks.flag("traction", traction) and pace is not None else None


def paced_control(sim: Simulator, z: np.ndarray, h: np.ndarray, speed: float, target: float, steer: float,
                  top: float, pace: Optional[float], grip: Optional[float] = None,
                  traction: Optional[Wheelspin] = None, limit: float = np.inf) -> tuple[float, float]:
    """``(gas, brake)`` for the ``target`` an agent chose at the state ``(z, h)``: with ``pace``,
    through ``racing_pace`` (with ``grip``) and ``speed_control``'s traction rule for ``steer``,
    the gas then through the drive's ``traction`` control where it has one; without, the plain
    ``speed_control`` (with the traction rule and control where ``traction`` is given: the
    learnt driver's). Never faster than ``limit`` (a planner's ``control.brake_ahead``)."""
    if pace is None:
        gas, brake = speed_control(speed, min(target, limit), None if traction is None else steer)
    else:
        paced = min(racing_pace(sim, z, h, target, top, pace, steer, grip), limit)
        gas, brake = speed_control(speed, paced, steer)
    return (gas if traction is None else traction.gas(speed, gas)), brake


class ClonedAgent(ModelAgent):
    """Behavioural cloning: the model's policy (``Model.policy_width`` is not None) drives.
    ``act(frame, speed)`` encodes the view, asks the policy for the speed to drive at and the
    steering from the code and the transition's hidden state, then steps the transition with
    the code and the action taken (the speedometer's speed and that steering), as the policy's
    training data was built. Deterministic; about 4 ms per decision on one thread.

    **Racing pace**: where the model has a pace head (``Model.pace_width``, the default's has
    one) and ``pace`` is a speed, the policy still steers, and where its own speed is at the top
    of its trained range (the road ahead is clear to it) the car drives at the pace head's
    speed, at most ``pace`` (where the policy slows for a bend, at the lower of the two), with
    less gas the more the wheels are turned (``speed_control``'s ``steer``); where that is faster
    than the policy's own speed, at most ``grip`` times the expert's grip envelope for the
    steering (``control.grip_speed``: a car steered harder than the expert ever was at that speed
    slides off and spins). ``pace=None`` drives at the policy's speed alone, as before the head;
    ``grip=None`` paces without the envelope; ``traction`` (at racing pace) cuts the gas where the
    wheels spin (``control.Wheelspin``); ``bearings``, where the car has lost the road, steers
    for the road still to drive in sight or turns until road lies ahead (``bearings.Bearings``)."""

    def __init__(self, model: Optional[Model] = None, threads: int = 1, pace: Optional[float] = PACE,
                 grip: Optional[float] = GRIP, traction: bool = True, bearings: bool = True):
        self.model = model if model is not None else Model.load()
        if self.model.policy_width is None:
            raise ValueError("the model has no policy (policy.* tensors): train one with `train policy`")
        self.pace, self.top = pace_option(self.model, pace), top_speed(self.model)
        self.grip, self.traction = grip_option(grip), traction_option(traction, self.pace)
        self.bearings = bearings_option(bearings)
        self.sim = Simulator(self.model, batch=1, threads=_checks.integer("threads", threads, 1))
        self.reset()

    def reset(self) -> None:
        """Forgets the drive: call at every new episode."""
        self.h = np.zeros(self.model.hidden_dim, np.float32)
        self.decisions = 0
        self.last_state: Optional[tuple] = None  # (z, h, speed) of the last decision
        for part in (self.traction, self.bearings):
            if part is not None:
                part.reset()

    def drive(self, frame: np.ndarray, z: np.ndarray, speed: float) -> np.ndarray:
        target, steer = self.decide(z)
        gas, brake = paced_control(self.sim, z, self.h, speed, target, steer, self.top, self.pace, self.grip,
                                   self.traction, self.speed_limit(z, speed, target, steer))
        self.last_state = (z, self.h, speed)
        _, self.h = self.sim.transition(z, self.h, np.array([speed, steer], np.float32))
        return np.array([steer, gas, brake], np.float32)

    def speed_limit(self, z: np.ndarray, speed: float, target: float, steer: float) -> float:
        """The fastest the car may go now, whatever the driver asks for: none here
        (``dreamt.DreamtAgent``'s ``anticipate`` sets one)."""
        return np.inf

    def paced(self, z: np.ndarray, target: float, steer: float = 0.0) -> float:
        """The speed to drive at with the pace head, for the policy's ``target`` and ``steer`` at
        the code ``z`` and the drive's hidden state (the class says how)."""
        return racing_pace(self.sim, z, self.h, target, self.top, self.pace, steer, self.grip)

    def decide(self, z: np.ndarray) -> tuple:
        """The speed to drive at and the steering (in [-1, 1]) for the code ``z`` of the frame
        seen now and the drive's hidden state: where a variant of the clone changes how it drives
        (``family.ChangedAgent``)."""
        return self.choose(z, self.h)

    def choose(self, z: np.ndarray, h: np.ndarray) -> tuple:
        """The speed to drive at and the steering for a code and a hidden state: the policy's
        (``dreamt.DreamtAgent``'s controller's), in the drive and in what it imagines."""
        target, steer = (float(v) for v in self.sim.act(z, h))
        return target, float(np.clip(steer, -1.0, 1.0))

    def imagine(self, steps: int = 8) -> Optional[np.ndarray]:
        """The policy driving on in the dream from the last decision, ``steps`` steps:
        ``(steps, 80, 160, 3)`` uint8 frames (for pictures, not for driving; the dream's speed
        is the one the car would reach, ``control.speed_after``). ``steps``: an integer >= 1."""
        steps = _checks.integer("steps", steps, 1)
        if self.last_state is None:
            return None
        z, h, speed = self.last_state
        codes = []
        for _ in range(steps):
            target, steer = self.choose(z, h)
            z, h = self.sim.transition(z, h, np.array([speed, steer], np.float32))
            speed = float(speed_after(speed, target))
            codes.append(z)
        return np.stack([self.sim.generate(code) for code in codes])

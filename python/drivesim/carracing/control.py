"""What every CarRacing agent shares: the checks of ``act``'s inputs, the warm-up while the env's
camera zooms in, the speed controller, and the proportional steering on the road seen now."""

from __future__ import annotations

from typing import Optional

import numpy as np

from .. import _checks

#: The models' view: what ``observe(env)`` returns and every agent's ``act`` takes.
FRAME_SHAPE = (80, 160, 3)
#: The largest speed an agent takes (Box2D units/s; CarRacing's car tops out near 100).
SPEED_MAX = 1000.0


def check_inputs(frame: np.ndarray, speed: float, shape: tuple = FRAME_SHAPE) -> tuple[np.ndarray, float]:
    """``act``'s arguments checked: the frame (C-ordered) and the speed as a float."""
    return _checks.frame(frame, shape), _checks.number("speed", speed, 0.0, SPEED_MAX)


#: The share of the gas ``speed_control`` takes off at full lock, given the steering (the
#: expert's traction rule, ``expert.TURN_GAS``): full gas with the wheels turned spins the car.
TURN_GAS = 0.5


def speed_control(speed: float, target: float, steer: Optional[float] = None) -> tuple[float, float]:
    """``(gas, brake)`` that bring ``speed`` to ``target`` (Box2D units/s; finite numbers,
    ValueError otherwise). With ``steer`` (the steering applied, in [-1, 1]), less gas the more
    the wheels are turned: ``TURN_GAS`` of it off at full lock (racing pace needs it)."""
    speed, target = _checks.number("speed", speed), _checks.number("target", target)
    gas = float(np.clip(0.06 * (target - speed), 0.0, 0.6))
    brake = float(np.clip(0.06 * (speed - target - 4.0), 0.0, 0.8))
    if steer is not None:
        steer = _checks.number("steer", steer, -1.0, 1.0)
        gas *= max(1.0 - TURN_GAS * abs(steer), 0.1)
    return gas, brake


#: The expert's grip envelope: the fastest it drives (the 99th percentile of its recorded speed,
#: units/s) at each amount of steering (``|steer|``, the centres of the bins), from its 12,800
#: racing-pace decisions (``python -m drivesim grip --episodes data/expert.safetensors.gz``).
#: Past it the car slides off and spins: racing pace keeps under it (``cloned.racing_pace``).
GRIP_STEER = (0.025, 0.075, 0.15, 0.25, 0.375, 0.525, 0.7, 0.9)
GRIP_SPEED = (95.3, 83.8, 68.8, 57.5, 54.3, 54.2, 49.8, 45.2)


def grip_speed(steer: float) -> float:
    """The grip envelope's speed (``GRIP_SPEED``) at the steering ``steer`` (in [-1, 1]; its
    size counts), interpolated between the bins, the ends held."""
    steer = _checks.number("steer", steer, -1.0, 1.0)
    return float(np.interp(abs(steer), GRIP_STEER, GRIP_SPEED))


def brake_ahead(steers, decel: float, grip: float = 1.0) -> float:
    """The fastest speed now from which a car that slows ``decel`` units/s a decision meets each
    steering of a plan (``steers``, one per decision from now) within ``grip`` times the grip
    envelope: the least of ``grip * grip_speed(steers[k]) + decel * k``. A planner that sees a
    bend ahead slows before it, where the envelope alone waits until the wheels are turned."""
    steers = _finite("steers", steers)
    if steers.ndim != 1 or len(steers) == 0 or (np.abs(steers) > 1.0).any():
        raise ValueError(f"steers: expected a plan (H,) of steerings in [-1, 1], got shape {steers.shape}")
    decel, grip = _checks.number("decel", decel, 0.0), _checks.number("grip", grip, 0.0, above=True)
    envelope = np.interp(np.abs(steers), GRIP_STEER, GRIP_SPEED)
    return float((grip * envelope + decel * np.arange(len(steers))).min())


class Wheelspin:
    """Traction control from the speedometer: gas that did not make a slow car faster means its
    rear wheels spin (after a slide, the car turns circles on the spot, on the grass or the road,
    for as long as the gas stays on). Then the gas is cut for a decision and held at most
    ``HOLD_GAS`` for ``HOLD`` decisions, so that the wheels grip and the car stops turning. One
    per drive: ``reset()`` at every episode, ``gas(speed, gas)`` at every decision."""

    #: Gas at least this, with the speed under ``BELOW`` rising less than ``RISE`` units/s in a
    #: decision, is a wheelspin (the car gains 2-6 units/s a decision under such gas when it grips).
    GAS, RISE, BELOW = 0.2, 0.5, 40.0
    #: Decisions the gas is held low after a wheelspin, and how low.
    HOLD, HOLD_GAS = 25, 0.2

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.last: Optional[tuple] = None  # (speed, gas) of the last decision
        self.held = 0
        self.spins = 0

    def gas(self, speed: float, gas: float) -> float:
        """The gas to apply at ``speed`` for the ``gas`` asked."""
        if self.last is not None:
            last_speed, last_gas = self.last
            if last_gas >= self.GAS and speed - last_speed < self.RISE and speed < self.BELOW:
                gas, self.held, self.spins = 0.0, self.HOLD, self.spins + 1
            elif self.held > 0:
                gas, self.held = min(gas, self.HOLD_GAS), self.held - 1
        self.last = (speed, gas)
        return gas


#: How the car's speed answers ``speed_control`` in one decision (4 frames), fitted on the clones'
#: drives of tracks 6000-6001 and 6005 (``python -m drivesim speed-model``): it gains at most
#: ``ACCELERATION`` units/s, a ``GAIN`` of the gap below that; it keeps its speed while the
#: target is at most ``BRAKE_DEAD`` below it (``speed_control``'s dead band) and reaches a target
#: further below within the decision.
ACCELERATION, GAIN, BRAKE_DEAD = 2.0, 0.2, 4.0


def speed_after(speed, target) -> np.ndarray:
    """The speed a decision after ``speed`` with ``speed_control`` driving to ``target``
    (numbers or arrays that broadcast; ValueError for what is not finite)."""
    return _speed_after(_finite("speed", speed), _finite("target", target))


def _speed_after(speed: np.ndarray, target: np.ndarray) -> np.ndarray:
    gap = target - speed
    return speed + np.where(gap >= 0.0, np.minimum(GAIN * gap, ACCELERATION), np.where(gap < -BRAKE_DEAD, gap, 0.0))


def speeds_reached(speed: float, targets: np.ndarray) -> np.ndarray:
    """The speed at the start of each decision of a plan, from ``speed`` now and the plan's
    target speeds ``targets`` ``(..., H)``: what the dream is stepped with (the transition
    learnt from the speedometer's speed), not the targets themselves, which a policy or a
    planner may set far above what the car reaches in a decision."""
    targets = _finite("targets", targets).astype(np.float32)
    if targets.ndim == 0:
        raise ValueError("targets: expected an array (..., H) of target speeds, got a number")
    out = np.empty(targets.shape, np.float32)
    now = np.full(targets.shape[:-1], _checks.number("speed", speed), np.float32)
    for t in range(targets.shape[-1]):
        out[..., t] = now
        now = _speed_after(now, targets[..., t]).astype(np.float32)  # checked above
    return out


def _finite(name: str, value) -> np.ndarray:
    value = _checks.floats(name, value)
    if not np.isfinite(value).all():
        raise ValueError(f"{name}: expected finite numbers")
    return value


def warmup_action(agent, speed: float) -> Optional[np.ndarray]:
    """Counts the agent's decision; while there have been at most ``agent.warmup`` (the env's
    first second, its camera zooming in: frames unlike anything the models saw), the action
    that drives straight at 25 units/s, else None."""
    agent.decisions += 1
    if agent.decisions > agent.warmup:
        return None
    gas, brake = speed_control(speed, 25.0)
    return np.array([0.0, gas, brake], np.float32)


class ModelAgent:
    """What the agents that read the models share: a decision every ``frame_skip`` env frames,
    the warm-up, and ``act``'s preamble (the inputs checked against the model's view, the
    warm-up's action, the view encoded) and its end (the ``bearings``' turns). A subclass has
    ``model`` and ``sim`` and gives ``drive(frame, z, speed)``: the action for the checked view,
    its code and the speed."""

    #: Env frames per decision: the models step at 12.5 Hz, CarRacing at 50.
    frame_skip = 4
    #: Decisions at the start spent driving straight while the env's camera zooms in (its
    #: first second): the zoomed-out frames are unlike anything the models saw, and the
    #: recorder starts its episodes after them.
    warmup = 12
    #: The drive's ``bearings.Bearings`` (the agent's ``bearings`` option), or None.
    bearings = None

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        """CarRacing's action ``[steer, gas, brake]`` for this view and speed."""
        frame, speed = check_inputs(frame, speed, self.model.frame_shape)
        warming_up = warmup_action(self, speed)
        if warming_up is not None:
            return warming_up
        action = self.drive(frame, self.sim.encode(frame), speed)
        # The driver decides (and steps its memory) at every decision; while the bearings turn
        # the car, their action is applied instead.
        return action if self.bearings is None else self.bearings.act(frame, speed, action)


def _road(road: np.ndarray) -> np.ndarray:
    road = _checks.floats("road", road)
    if road.shape != (4,) or not np.isfinite(road).all():
        raise ValueError(f"road: expected 4 finite figures (road.measure's), got {road}")
    return road


def proportional_steering(road: np.ndarray) -> float:
    """Steering toward the road's centre as measured in the near and middle bands (pixels;
    positive: road to the right, so steer right). ``road``: one row of ``road.measure``."""
    road = _road(road)
    return float(np.clip(0.02 * road[0] + 0.03 * road[1], -1.0, 1.0))


def target_speed(road: np.ndarray, max_speed: float, half_width: float) -> float:
    """Slower as the road ahead bends: the far band's offset from the near band's."""
    road = _road(road)
    max_speed = _checks.number("max_speed", max_speed, 0.0, above=True)
    half_width = _checks.number("half_width", half_width, 0.0, above=True)
    bend = abs(float(road[2] - road[0])) / half_width
    return float(np.clip(max_speed / (1.0 + 4.0 * bend), 20.0, max_speed))

"""Agents that drive gymnasium's CarRacing from the models' view and the speedometer alone.

``MPCAgent`` ("mpc") plans in the simulator: it encodes each real frame, rebuilds the
transition's hidden state from the last few real codes and actions (as a dream is seeded),
rolls candidate steering ramps out in the dream (``Simulator.rollout_candidates``, codes only)
on a grid centred on a proportional steering toward the road seen now, scores each dreamed
future with the ``RoadCost`` (the road's centre in the near and middle bands, road under the
car), corrected by what the cost gets wrong on the real frame now (offset-free MPC), refines
the grid once around the best, and applies the best plan's first steering. The speed follows a
target that falls as the road ahead bends, through a proportional speed controller (target
speed to gas and brake).

``ClonedAgent`` ("cloned") drives as its teacher did: behavioural cloning (the default's policy:
the privileged expert and three DAgger rounds, ``weights/dagger.py``), the policy in the weight
file (``Simulator.act``, trained by ``train policy``) reading the code of the frame
seen now and the transition's hidden state stepped along the drive, and giving the steering and
the speed to drive at (through the same speed controller).

``ReactiveAgent`` ("reactive") is the baseline without the models: the proportional steering
and the speed controller alone.

Every agent checks its options when it is made and its inputs at every ``act``, the warm-up
decisions included: ``frame`` must be the models' view, a uint8 array ``(80, 160, 3)``
(ValueError otherwise), and ``speed`` the speedometer, a finite number from 0 to
``SPEED_MAX`` (TypeError for what is not a number, ValueError otherwise). Actions are finite.
"""

from __future__ import annotations

from collections import deque
from typing import Optional

import numpy as np

from .. import _checks
from .._drivesim import Model, Simulator
from ..road import RoadCost, measure

#: The models' view: what ``observe(env)`` returns and every agent's ``act`` takes.
FRAME_SHAPE = (80, 160, 3)
#: The largest speed an agent takes (Box2D units/s; CarRacing's car tops out near 100).
SPEED_MAX = 1000.0


def check_inputs(frame: np.ndarray, speed: float, shape: tuple = FRAME_SHAPE) -> tuple[np.ndarray, float]:
    """``act``'s arguments checked: the frame (C-ordered) and the speed as a float."""
    return _checks.frame(frame, shape), _checks.number("speed", speed, 0.0, SPEED_MAX)


def speed_control(speed: float, target: float) -> tuple[float, float]:
    """``(gas, brake)`` that bring ``speed`` to ``target`` (Box2D units/s; finite numbers,
    ValueError otherwise)."""
    speed, target = _checks.number("speed", speed), _checks.number("target", target)
    gas = float(np.clip(0.06 * (target - speed), 0.0, 0.6))
    brake = float(np.clip(0.06 * (speed - target - 4.0), 0.0, 0.8))
    return gas, brake


def warmup_action(agent, speed: float) -> Optional[np.ndarray]:
    """Counts the agent's decision; while there have been at most ``agent.warmup`` (the env's
    first second, its camera zooming in: frames unlike anything the models saw), the action
    that drives straight at 25 units/s, else None."""
    agent.decisions += 1
    if agent.decisions > agent.warmup:
        return None
    gas, brake = speed_control(speed, 25.0)
    return np.array([0.0, gas, brake], np.float32)


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


class ClonedAgent:
    """Behavioural cloning: the model's policy (``Model.policy_width`` is not None) drives.
    ``act(frame, speed)`` encodes the view, asks the policy for the speed to drive at and the
    steering from the code and the transition's hidden state, then steps the transition with
    the code and the action taken (the speedometer's speed and that steering), as the policy's
    training data was built. Deterministic; about 4 ms per decision on one thread."""

    frame_skip = 4
    #: Decisions at the start driving straight while the env's camera zooms in, as the recorder
    #: does before its episodes begin.
    warmup = 12

    def __init__(self, model: Optional[Model] = None, threads: int = 1):
        self.model = model if model is not None else Model.load()
        if self.model.policy_width is None:
            raise ValueError("the model has no policy (policy.* tensors): train one with `train policy`")
        self.sim = Simulator(self.model, batch=1, threads=_checks.integer("threads", threads, 1))
        self.reset()

    def reset(self) -> None:
        """Forgets the drive: call at every new episode."""
        self.h = np.zeros(self.model.hidden_dim, np.float32)
        self.decisions = 0
        self.last_state: Optional[tuple] = None  # (z, h, speed) of the last decision

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        """CarRacing's action ``[steer, gas, brake]`` for this view and speed."""
        frame, speed = check_inputs(frame, speed, self.model.frame_shape)
        warming_up = warmup_action(self, speed)
        if warming_up is not None:
            return warming_up
        z = self.sim.encode(frame)
        target, steer = (float(v) for v in self.sim.act(z, self.h))
        steer = float(np.clip(steer, -1.0, 1.0))
        self.last_state = (z, self.h, speed)
        _, self.h = self.sim.transition(z, self.h, np.array([speed, steer], np.float32))
        gas, brake = speed_control(speed, target)
        return np.array([steer, gas, brake], np.float32)

    def imagine(self, steps: int = 8) -> Optional[np.ndarray]:
        """The policy driving on in the dream from the last decision, ``steps`` steps:
        ``(steps, 80, 160, 3)`` uint8 frames (for pictures, not for driving; the dream's speed
        is the speed the policy asks for). ``steps``: an integer >= 1."""
        steps = _checks.integer("steps", steps, 1)
        if self.last_state is None:
            return None
        z, h, speed = self.last_state
        codes = []
        for _ in range(steps):
            target, steer = (float(v) for v in self.sim.act(z, h))
            z, h = self.sim.transition(z, h, np.array([speed, steer], np.float32))
            speed = target
            codes.append(z)
        return np.stack([self.sim.generate(code) for code in codes])


class MPCAgent:
    """Model-predictive control in the dream. ``act(frame, speed)`` takes the models' view
    (``observe(env)``, ``(80, 160, 3)`` uint8) and the speedometer, and returns CarRacing's
    action ``[steer, gas, brake]`` (float32) to hold for ``frame_skip`` env frames.

    Deterministic: the candidates are a fixed grid around the proportional steering, and the
    simulator is bit-identical whatever the thread count.

    Options (ValueError outside these, TypeError for the wrong kind): ``candidates`` an integer
    from 4 to 4096 (the grid is ``rows`` first steerings by ``candidates // rows`` ramps, ``rows
    = max(2, candidates // 4)``: 64 is 16 by 4, and a count that fills no grid uses the largest
    that fits); ``horizon`` 1 to 1000; ``iterations`` 1 to 100; ``context`` 0 to 1000; ``skip``
    0 to ``horizon - 1``; ``threads`` 1 to 1024; ``max_speed`` (at most ``SPEED_MAX``),
    ``road_scale`` and ``search`` finite and > 0; the weights ``w_*`` and ``correct`` finite
    and >= 0.
    """

    #: Env frames per decision: the models step at 12.5 Hz, CarRacing at 50.
    frame_skip = 4
    #: Decisions at the start spent driving straight while the env's camera zooms in (its
    #: first second): the zoomed-out frames are unlike anything the models saw.
    warmup = 12

    def __init__(
        self,
        model: Optional[Model] = None,
        cost: Optional[RoadCost] = None,
        threads: int = 1,
        candidates: int = 64,
        horizon: int = 8,
        iterations: int = 2,
        context: int = 5,
        max_speed: float = 52.0,
        road_scale: float = 20.0,
        w_middle: float = 1.0,
        w_off: float = 2.0,
        w_smooth: float = 0.0,
        correct: float = 1.0,
        w_effort: float = 0.0,
        w_prior: float = 4.0,
        search: float = 0.3,
        skip: int = 3,
    ):
        count, number = _checks.integer, _checks.number
        candidates, horizon = count("candidates", candidates, 4, 4096), count("horizon", horizon, 1, 1000)
        iterations, context = count("iterations", iterations, 1, 100), count("context", context, 0, 1000)
        skip, threads = count("skip", skip, 0, horizon - 1), count("threads", threads, 1)
        max_speed = number("max_speed", max_speed, 0.0, SPEED_MAX, above=True)
        road_scale, search = number("road_scale", road_scale, 0.0, above=True), number("search", search, 0.0, above=True)
        w_middle, w_off, w_smooth = (number(n, v, 0.0) for n, v in (("w_middle", w_middle), ("w_off", w_off), ("w_smooth", w_smooth)))
        correct, w_effort, w_prior = (number(n, v, 0.0) for n, v in (("correct", correct), ("w_effort", w_effort), ("w_prior", w_prior)))
        self.model = model if model is not None else Model.load()
        self.cost = cost if cost is not None else RoadCost.default()
        self.sim = Simulator(self.model, batch=candidates, threads=threads)
        self.candidates, self.horizon, self.iterations = candidates, horizon, iterations
        rows = max(2, candidates // 4)
        self.grid = (rows, candidates // rows)  # first steerings by ramps: at most `candidates`
        self.context, self.max_speed = context, max_speed
        # The cost: offsets in units of `road_scale` pixels (about a half-road), weights of the
        # middle band, of road missing under the car and of steering changes.
        self.road_scale, self.w_middle, self.w_off, self.w_smooth = road_scale, w_middle, w_off, w_smooth
        self.correct, self.w_effort, self.w_prior, self.search = correct, w_effort, w_prior, search
        self.prior = 0.0
        self.skip = skip
        self.half_width = self.model.frame_shape[1] / 2
        self.reset()

    def reset(self) -> None:
        """Forgets the drive: call at every new episode."""
        self.past: deque = deque(maxlen=self.context)  # (code, action) of recent decisions
        self.chosen = np.zeros(self.horizon, np.float32)  # the last chosen steering plan
        self.previous = 0.0  # the last steering applied
        self.decisions = 0
        self.last_plan: Optional[np.ndarray] = None  # (horizon, 2) actions of the chosen plan
        self.last_state: Optional[tuple] = None  # (h, z) the plan started from

    def _hidden(self, z: np.ndarray) -> np.ndarray:
        """The hidden state after teacher-forcing the recent real codes and actions from zero,
        as a rollout is seeded: the transition was trained on short windows from zero."""
        h = np.zeros(self.model.hidden_dim, np.float32)
        for code, action in self.past:
            _, h = self.sim.transition(code, h, action)
        return h

    def plan(self, h: np.ndarray, z: np.ndarray, speed: float, correction: np.ndarray) -> np.ndarray:
        """The chosen steering sequence ``(horizon,)``: ramps from a first steering ``a`` to a
        last ``a + b``, searched on a grid of ``rows`` by ``cols`` (``self.grid``, at most
        ``candidates``) in ``iterations`` rounds, each finer and centred on the last round's
        best. Few degrees of freedom keep the plans smooth, so the planner cannot exploit the
        dream's step-to-step errors."""
        (rows, cols), t = self.grid, self.horizon
        actions = np.empty((t, rows * cols, 2), np.float32)
        actions[..., 0] = np.float32(np.clip(speed, *self._speed_range()))
        ramp = np.linspace(0.0, 1.0, t, dtype=np.float32)
        weights = np.linspace(0.5, 1.0, t, dtype=np.float32)[:, None]
        # The first steps are left out: there the dream repeats its data's correlation (drivers
        # steer toward where the road already is) more than the steering's effect.
        weights[: self.skip] = 0.0
        centre = np.float32([self.prior if self.w_prior > 0 else self.previous, 0.0])
        width = np.float32([self.search, 1.0])
        for _ in range(self.iterations):
            a = np.clip(centre[0] + width[0] * np.linspace(-1, 1, rows), -1, 1)
            b = centre[1] + width[1] * np.linspace(-1, 1, cols)
            a, b = (g.ravel().astype(np.float32) for g in np.meshgrid(a, b))
            steer = np.clip(a[:, None] + b[:, None] * ramp, -1.0, 1.0)  # (n, t)
            actions[..., 1] = steer.T
            road = self.cost.predict(self.sim.rollout_candidates(h, actions, z=z)) + correction  # (t, n, 4)
            near, middle = road[..., 0] / self.road_scale, road[..., 1] / self.road_scale
            off = np.clip(1.0 - road[..., 3] / 0.6, 0.0, 1.0)
            cost = (weights * (near**2 + self.w_middle * middle**2 + self.w_off * off**2)).sum(axis=0)
            cost += self.w_smooth * (a - self.previous) ** 2 + self.w_effort * (steer**2).mean(axis=1)
            cost += self.w_prior * (a - self.prior) ** 2
            best = int(np.argmin(cost))
            centre, width = np.float32([a[best], b[best]]), width / 4
            chosen = steer[best]
        self.chosen = chosen.astype(np.float32)
        return self.chosen

    def _speed_range(self) -> tuple[float, float]:
        specs = self.model.actions
        return (specs[0]["min"], specs[0]["max"]) if specs else (0.0, 100.0)

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        """CarRacing's action ``[steer, gas, brake]`` for this view and speed."""
        frame, speed = check_inputs(frame, speed, self.model.frame_shape)
        warming_up = warmup_action(self, speed)
        if warming_up is not None:
            return warming_up
        z = self.sim.encode(frame)
        h = self._hidden(z)
        # Offset-free MPC: the dream's road is corrected by what it gets wrong now (the road
        # measured on the real frame less the road read from its code), a disturbance held
        # constant over the horizon. Off the road the encoder still draws road under the car;
        # the measured frame does not.
        road_now = measure(frame[None])[0]
        correction = (road_now - self.cost.predict(z)) * self.correct
        # A proportional steering on the road seen now: where the search is centred.
        self.prior = proportional_steering(road_now)
        steer_plan = self.plan(h, z, speed, correction.astype(np.float32))
        steer = float(steer_plan[0])
        self.previous = steer
        gas, brake = speed_control(speed, target_speed(road_now, self.max_speed, self.half_width))
        self.past.append((z, np.array([speed, steer], np.float32)))
        self.last_state = (h, z)
        self.last_plan = np.stack([np.full(self.horizon, speed, np.float32), steer_plan], axis=1)
        return np.array([steer, gas, brake], np.float32)

    def imagine(self) -> Optional[np.ndarray]:
        """The dream of the last chosen plan: ``(horizon, 80, 160, 3)`` uint8 frames (a
        generator pass per step: for pictures, not for driving)."""
        if self.last_plan is None:
            return None
        h, z = self.last_state
        _, frames = self.sim.rollout_candidates(h, self.last_plan[:, None, :].copy(), z=z, frames=True)
        return frames[:, 0]


AGENTS = {"mpc": MPCAgent, "cloned": ClonedAgent, "reactive": ReactiveAgent, "random": RandomAgent}


def make_agent(name: str, weights: Optional[str] = None, threads: int = 1, **options):
    """An agent by name: ``"mpc"`` (planning in the simulator), ``"cloned"`` (the policy in the
    weight file), or the baselines without the models, ``"reactive"`` and ``"random"``.
    ``weights``: a weight file (the built-in default model when None; for ``"mpc"``, another
    model also needs ``cost=RoadCost...``). ``options`` are the agent's (``MPCAgent`` says
    which it takes); ValueError or TypeError for an option out of range or of the wrong kind."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}: one of {', '.join(sorted(AGENTS))}")
    if name not in ("mpc", "cloned"):
        return AGENTS[name](**options)
    model = Model.load(weights)
    return AGENTS[name](model=model, threads=threads, **options)

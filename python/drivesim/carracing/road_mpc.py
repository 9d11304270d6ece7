"""``RoadMPCAgent`` ("mpc-road"), the first planner: steering ramps on a grid scored by the
hand-fitted ``RoadCost`` in an 8-step mean dream. Kept for comparison with ``MPCAgent``
("mpc"), which plans with the learned reward and value heads (``agents.py`` says how they
compare)."""

from __future__ import annotations

from collections import deque
from typing import Optional

import numpy as np

from .. import _checks
from .._drivesim import Model, Simulator
from ..road import RoadCost, measure
from .control import SPEED_MAX, ModelAgent, proportional_steering, speed_control, target_speed


class RoadMPCAgent(ModelAgent):
    """Model-predictive control in the dream, on a grid of steering ramps scored by
    ``RoadCost``. ``act(frame, speed)`` takes the models' view (``observe(env)``, ``(80, 160,
    3)`` uint8) and the speedometer, and returns CarRacing's action ``[steer, gas, brake]``
    (float32) to hold for ``frame_skip`` env frames.

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

    def drive(self, frame: np.ndarray, z: np.ndarray, speed: float) -> np.ndarray:
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

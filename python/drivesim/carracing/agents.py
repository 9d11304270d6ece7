"""Agents that drive gymnasium's CarRacing from the models' view and the speedometer alone.

``MPCAgent`` ("mpc") plans in the simulator: it encodes each real frame, rebuilds the
transition's hidden state from the last few real codes and actions (as a dream is seeded),
rolls candidate steering sequences out in the dream (``Simulator.rollout_candidates``, codes
only), scores each dreamed future with the ``RoadCost`` (how far the road's centre is from the
car in three bands ahead, and whether road is under it), refines them by the cross-entropy
method, and applies the best plan's first steering. The speed follows a target that falls as
the road ahead bends (read from the real frame's code by the same cost), through a
proportional speed controller (target speed to gas and brake).
"""

from __future__ import annotations

from collections import deque
from typing import Optional

import numpy as np

from .._drivesim import Model, Simulator
from ..road import RoadCost


def speed_control(speed: float, target: float) -> tuple[float, float]:
    """``(gas, brake)`` that bring ``speed`` to ``target`` (Box2D units/s)."""
    gas = float(np.clip(0.06 * (target - speed), 0.0, 0.6))
    brake = float(np.clip(0.06 * (speed - target - 4.0), 0.0, 0.8))
    return gas, brake


class MPCAgent:
    """Model-predictive control in the dream. ``act(frame, speed)`` takes the models' view
    (``observe(env)``, ``(80, 160, 3)`` uint8) and the speedometer, and returns CarRacing's
    action ``[steer, gas, brake]`` (float32) to hold for ``frame_skip`` env frames.

    Deterministic for a given ``seed``: the candidates are drawn from a generator reset by
    ``reset()``, and the simulator is bit-identical whatever the thread count.
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
        iterations: int = 3,
        context: int = 5,
        max_speed: float = 58.0,
        seed: int = 0,
    ):
        self.model = model if model is not None else Model.load()
        self.cost = cost if cost is not None else RoadCost.default()
        self.sim = Simulator(self.model, batch=candidates, threads=threads)
        self.candidates, self.horizon, self.iterations = candidates, horizon, iterations
        self.context, self.max_speed, self.seed = context, max_speed, seed
        self.half_width = self.model.frame_shape[1] / 2
        self.reset()

    def reset(self) -> None:
        """Forgets the drive: call at every new episode."""
        self.rng = np.random.default_rng(self.seed)
        self.past: deque = deque(maxlen=self.context)  # (code, action) of recent decisions
        self.mean = np.zeros(self.horizon, np.float32)
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

    def target_speed(self, road: np.ndarray) -> float:
        """Slower as the road ahead bends: the far band's offset from the near band's."""
        bend = abs(float(road[2] - road[0])) / self.half_width
        return float(np.clip(self.max_speed / (1.0 + 4.0 * bend), 20.0, self.max_speed))

    def plan(self, h: np.ndarray, z: np.ndarray, speed: float) -> np.ndarray:
        """The cross-entropy method over steering sequences: the chosen ``(horizon,)``."""
        n, t = self.candidates, self.horizon
        mean = np.concatenate([self.mean[1:], self.mean[-1:]])
        std = np.full(t, 0.4, np.float32)
        actions = np.empty((t, n, 2), np.float32)
        actions[..., 0] = np.float32(np.clip(speed, *self._speed_range()))
        weights = np.linspace(1.0, 0.5, t, dtype=np.float32)[:, None]
        for _ in range(self.iterations):
            steer = np.clip(mean + std * self.rng.standard_normal((n, t)), -1.0, 1.0).astype(np.float32)
            steer[0] = mean
            actions[..., 1] = steer.T
            road = self.cost.predict(self.sim.rollout_candidates(h, actions, z=z))  # (t, n, 4)
            near, middle = road[..., 0] / self.half_width, road[..., 1] / self.half_width
            off = np.clip(1.0 - road[..., 3] / 0.6, 0.0, 1.0)
            cost = (weights * (4.0 * near**2 + middle**2 + 4.0 * off**2)).sum(axis=0)
            cost += 0.2 * (np.diff(steer, axis=1) ** 2).sum(axis=1)
            elite = steer[np.argsort(cost)[: max(2, n // 8)]]
            mean, std = elite.mean(axis=0), elite.std(axis=0) + 0.05
        self.mean = mean.astype(np.float32)
        return self.mean

    def _speed_range(self) -> tuple[float, float]:
        specs = self.model.actions
        return (specs[0]["min"], specs[0]["max"]) if specs else (0.0, 100.0)

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        """CarRacing's action ``[steer, gas, brake]`` for this view and speed."""
        self.decisions += 1
        if self.decisions <= self.warmup:
            gas, brake = speed_control(speed, 25.0)
            return np.array([0.0, gas, brake], np.float32)
        z = self.sim.encode(frame)
        h = self._hidden(z)
        steer_plan = self.plan(h, z, speed)
        steer = float(steer_plan[0])
        road_now = self.cost.predict(z)
        gas, brake = speed_control(speed, self.target_speed(road_now))
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


AGENTS = {"mpc": MPCAgent}


def make_agent(name: str, weights: Optional[str] = None, threads: int = 1, **options):
    """An agent by name: ``"mpc"`` (planning in the simulator). ``weights``: a weight file (the
    built-in default model when None; another model also needs ``cost=RoadCost...``)."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}: one of {', '.join(sorted(AGENTS))}")
    model = Model.load(weights)
    return AGENTS[name](model=model, threads=threads, **options)

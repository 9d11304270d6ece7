"""A driver learnt inside the dream (issue 60): the controller, its rollouts in the dream, and the
agent that drives the real CarRacing with it. ``dream_train`` trains it. The agent also drives
a weight file's policy head without a controller: the driver that ``weights/tool train driver``
learns in the dream by the gradient of its return, written in the policy's place.

The controller reads what the cloned policy reads, the code ``z`` of the frame seen now and the
transition's hidden state ``h``, through a fixed projection onto the first ``K`` principal
components of ``[z, h]`` over real states (a small controller, as World Models' linear one):

    f = P (([z, h] - centre) / scale)        K features of unit variance; P, centre, scale fixed
    u = W [f, 1]                             W: 2 x (K + 1), what training learns
    fresh:  target = a + (b - a) sigmoid(u_0),           steering = tanh(u_1)
    cloned: target = clone's + a tanh(u_0) (>= 0),       steering = clone's + b tanh(u_1)  (in [-1, 1])

with ``(a, b)`` the controller's ``limits``: a fresh one's range of target speeds, or the largest
change a controller on the clone makes to its target speed and its steering (a trust region).

``fresh`` never sees an expert's label; ``cloned`` starts from the cloned policy (W = 0 is the
clone) and only adds to it. The target speed drives ``speed_control`` as the clone's does.

A controller file (``.npz``): ``centre`` and ``scale`` ``[z_dim + hidden_dim]``, ``projection``
``[K, z_dim + hidden_dim]``, ``weights`` ``[2, K + 1]`` (float64), ``base`` ("fresh" or
"cloned"), ``limits`` ``[2]``, ``generation`` (int64).
"""

from __future__ import annotations

import os
from typing import Optional

import numpy as np

from .. import _checks
from .._drivesim import Model, Simulator
from .._files import atomic_write
from .cloned import ClonedAgent, top_speed
from .control import Wheelspin, brake_ahead, speed_after

BASES = ("fresh", "cloned")
#: A controller on the clone's ``limits`` unless told: up to 10 units/s of target speed and the
#: whole steering range.
CLONE_LIMITS = (10.0, 1.0)
#: Decisions ahead that ``DreamtAgent``'s ``anticipate`` dreams its own plan (``mpc``'s horizon).
ANTICIPATE_HORIZON = 8


class Controller:
    """The projection and the weights of a controller (see the module); ``weights`` may hold a
    population, ``[P, 2, K + 1]``, for a batch of drives."""

    def __init__(self, centre, scale, projection, weights, base: str = "fresh", limits=(10.0, 58.8),
                 generation: int = 0):
        self.centre = np.asarray(centre, np.float32)
        self.scale = np.asarray(scale, np.float32)
        self.projection = np.asarray(projection, np.float32)
        self.weights = np.asarray(weights, np.float64)
        self.base, self.generation = base, int(generation)
        self.limits = np.asarray(limits, np.float64)
        k, d = self.projection.shape
        if (self.centre.shape != (d,) or self.scale.shape != (d,) or self.weights.shape[-2:] != (2, k + 1)
                or self.limits.shape != (2,) or base not in BASES):
            raise ValueError(f"a controller whose parts disagree: projection {self.projection.shape}, centre "
                             f"{self.centre.shape}, scale {self.scale.shape}, weights {self.weights.shape}, base {base!r}")
        for name in ("centre", "scale", "projection", "weights", "limits"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"controller: {name} is not finite")
        if (self.scale <= 0).any():
            raise ValueError("controller: scales must be positive")
        a, b = self.limits
        if not (0 <= a < b if base == "fresh" else a >= 0 and 0 <= b <= 2):
            raise ValueError(f"controller: limits {a}, {b}: a fresh one's are a range of speeds, a cloned one's "
                             "a largest change of speed (>= 0) and of steering (0 to 2)")

    @classmethod
    def fit(cls, z: np.ndarray, h: np.ndarray, features: int, base: str, limits) -> "Controller":
        """A controller of weights 0 whose projection is fitted on real states ``z``, ``h``."""
        x = np.concatenate([z, h], axis=1).astype(np.float64)
        centre, scale = x.mean(axis=0), x.std(axis=0) + 1e-6
        standard = (x - centre) / scale
        values, vectors = np.linalg.eigh(standard.T @ standard / len(x))
        # The largest components first, each scaled to unit variance over the states: a
        # weight of 1 moves u by one standard deviation of its feature.
        order = np.argsort(values)[::-1][:features]
        projection = vectors[:, order].T / np.sqrt(np.maximum(values[order], 1e-12))[:, None]
        return cls(centre, scale, projection, np.zeros((2, features + 1)), base, limits)

    @property
    def size(self) -> int:
        """The numbers training learns: ``2 (K + 1)``."""
        return 2 * (self.projection.shape[0] + 1)

    def features(self, z: np.ndarray, h: np.ndarray) -> np.ndarray:
        """``[N, K + 1]``: the projected states and a 1."""
        x = (np.concatenate([z, h], axis=-1) - self.centre) / self.scale
        f = x @ self.projection.T
        return np.concatenate([f, np.ones(f.shape[:-1] + (1,), f.dtype)], axis=-1).astype(np.float64)

    def decide(self, features: np.ndarray, clone: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
        """``(target speeds, steering)`` for ``features`` ``[..., K + 1]`` (``[P, S, K + 1]`` with
        a population's weights): ``clone`` the cloned policy's actions there (``cloned``)."""
        u = np.einsum("...jk,...sk->...sj", self.weights, features) if self.weights.ndim == 3 \
            else features @ self.weights.T
        a, b = self.limits
        if self.base == "fresh":
            return a + (b - a) / (1 + np.exp(-u[..., 0])), np.tanh(u[..., 1])
        clone = np.asarray(clone, np.float64).reshape(u.shape)
        return (np.maximum(clone[..., 0] + a * np.tanh(u[..., 0]), 0.0),
                np.clip(clone[..., 1] + b * np.tanh(u[..., 1]), -1.0, 1.0))

    def with_weights(self, weights: np.ndarray, generation: int) -> "Controller":
        return Controller(self.centre, self.scale, self.projection, weights, self.base, self.limits, generation)

    def save(self, path) -> None:
        with atomic_write(path) as f:
            np.savez(f, centre=self.centre, scale=self.scale, projection=self.projection, weights=self.weights,
                     base=np.array(self.base), limits=self.limits, generation=np.int64(self.generation))

    @classmethod
    def load(cls, path) -> "Controller":
        """A controller file (ValueError naming the file for what is not one)."""
        try:
            with np.load(os.fspath(path), allow_pickle=False) as f:
                parts = {k: f[k] for k in ("centre", "scale", "projection", "weights", "base", "limits", "generation")}
        except (OSError, KeyError, ValueError, EOFError) as error:
            raise ValueError(f"{path}: not a controller file ({error})") from None
        if parts["weights"].ndim != 2:
            raise ValueError(f"{path}: a controller holds one set of weights")
        try:
            return cls(parts["centre"], parts["scale"], parts["projection"], parts["weights"], str(parts["base"]),
                       parts["limits"], int(parts["generation"]))
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None


def default_limits(model: Model, base: str) -> tuple[float, float]:
    """A fresh controller's target speeds, 10 to the model's top speed; a cloned one's
    ``CLONE_LIMITS``."""
    if base == "cloned":
        return CLONE_LIMITS
    specs = model.actions
    return 10.0, float(specs[0]["max"]) if specs else 58.8


def rollout(world: Simulator, controller: Controller, starts: dict, horizon: int, off_road_steps: int = 0,
            use_value: bool = False, off_road_cost: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Every controller of the population (``controller.weights`` ``[P, 2, K + 1]``) from every
    start (``starts``: ``z``, ``h``, ``speed``, S each), ``horizon`` decisions, in one batch of
    P x S drives on ``world`` (sampled where its sampling is on, the noise of each drive's item
    at step ``t``; every controller starts from the same states, each meets noise of its own):
    ``(returns, off-road chances)`` ``[P, S]``. The reward head's rewards are summed, less
    ``off_road_cost`` times the off-road chance of each decision; with ``off_road_steps`` a
    drive earns nothing once its off-road chance has been above one half that many decisions
    in a row; ``use_value`` adds the value head at the horizon to the drives still going."""
    p, s = controller.weights.shape[0], len(starts["speed"])
    z = np.ascontiguousarray(np.tile(starts["z"], (p, 1)), np.float32)
    h = np.ascontiguousarray(np.tile(starts["h"], (p, 1)), np.float32)
    v = np.tile(starts["speed"], p).astype(np.float32)
    total, off, off_for = np.zeros(p * s), np.zeros(p * s), np.zeros(p * s, np.int64)
    going = np.ones(p * s, bool)
    for step in range(horizon):
        f = controller.features(z, h).reshape(p, s, -1)
        clone = world.act(z, h) if controller.base == "cloned" else None
        target, steer = (a.reshape(-1) for a in controller.decide(f, clone))
        action = np.ascontiguousarray(np.stack([v, steer], 1), np.float32)
        z, h = world.transition(z, h, action)
        if world.sampling[0] > 0:
            z = world.sample(h, step, z)
        v = speed_after(v, target).astype(np.float32)
        reward = world.reward(z, h)
        total += np.where(going, reward[:, 0] - off_road_cost * reward[:, 1], 0.0)
        off += reward[:, 1]
        if off_road_steps:
            off_for = np.where(reward[:, 1] > 0.5, off_for + 1, 0)
            going &= off_for < off_road_steps
    if use_value:
        total += np.where(going, world.value(z, h)[:, 0], 0.0)
    return total.reshape(p, s), (off / horizon).reshape(p, s)


def driven_model(weights=None, driver=None, controller=None) -> Model:
    """The model a ``dreamt`` agent drives: the world of ``weights`` (the default's when None)
    with ``driver`` (a driver file, ``drivesim.driver``) as its policy; with neither, nor a
    ``controller``, the built-in driver learnt in the default's dream (``Model.dreamt()``)."""
    if driver is not None:
        return Model.load(weights, driver=driver)
    if weights is None and controller is None:
        return Model.dreamt()
    return Model.load(weights)


class DreamtAgent(ClonedAgent):
    """The driver learnt in the dream: ``controller`` (a controller file of ``dream-train``)
    decides from the code of the view and the transition's hidden state, which steps as the
    cloned agent's does; without one, the model's policy head drives (a driver that
    ``weights/tool train driver`` learnt in the dream: the built-in one, ``Model.dreamt()``, when
    no model is given), at its own speed: no racing pace, grip envelope or bearings, none of
    which it learnt with. A model whose policy is the clone (it has the pace head) is refused.
    ``traction`` gives its speed control the traction of the clone's racing pace (less gas with
    the wheels turned, ``control.speed_control``, and the gas cut while the rear wheels spin,
    ``control.Wheelspin``): below the driver's decisions, it changes neither its speed nor its
    steering, only how the pedals reach them. None: on for a policy head (the gradient's drivers
    were learnt and scored with it), off for a controller (CMA-ES's were scored without).

    ``anticipate=D`` (units/s a decision, 0 to 100; None: off) dreams the driver's own next
    ``ANTICIPATE_HORIZON`` decisions from each state (the mean dream) and keeps the speed under
    ``control.brake_ahead`` of their steering, as ``mpc``'s option does: slow enough to meet each
    planned steering within the grip envelope, shedding D units/s a decision. It only lowers the
    speed the driver asks for.

    >>> from drivesim.carracing import make_agent
    >>> agent = make_agent("dreamt")   # the built-in driver, learnt only in the default's dream
    >>> agent.traction is not None
    True
    """

    def __init__(self, model: Optional[Model] = None, threads: int = 1, controller=None,
                 traction: Optional[bool] = None, anticipate: Optional[float] = None):
        self.model = model if model is not None else driven_model(controller=controller)
        if controller is None:
            self.controller = None
            if self.model.policy_width is None:
                raise ValueError("dreamt: give controller=FILE (python -m drivesim dream-train writes one) or a "
                                 "weight file whose policy was learnt in the dream (weights/tool train driver)")
            if self.model.pace_width is not None:
                raise ValueError("dreamt: this model's policy is the cloned driver (it has the pace head); give a "
                                 "driver learnt in the dream (driver=FILE, or weights/tool train driver's weight "
                                 "file) or controller=FILE")
        else:
            self.controller = controller if isinstance(controller, Controller) else Controller.load(controller)
            if self.controller.base == "cloned" and self.model.policy_width is None:
                raise ValueError("a controller on the cloned policy needs a model with a policy")
            if self.controller.centre.shape != (self.model.z_dim + self.model.hidden_dim,):
                raise ValueError(f"the controller reads {self.controller.centre.shape[0]} numbers; the model's [z, h] "
                                 f"has {self.model.z_dim + self.model.hidden_dim}")
        if traction is None:
            traction = self.controller is None
        # The driver gives the speed: no racing pace, grip envelope or bearings. Traction is the
        # speed control's, below the driver's decisions: less gas with the wheels turned, and
        # none while the rear wheels spin (control.Wheelspin).
        self.pace, self.top, self.grip, self.bearings = None, top_speed(self.model), None, None
        self.traction = Wheelspin() if _checks.flag("traction", traction) else None
        self.anticipate = None if anticipate is None else _checks.number("anticipate", anticipate, 0.0, 100.0)
        self.sim = Simulator(self.model, batch=1, threads=_checks.integer("threads", threads, 1))
        self.reset()

    def speed_limit(self, z: np.ndarray, speed: float, target: float, steer: float) -> float:
        """With ``anticipate``, the fastest speed now that meets the steering of the driver's own
        plan, dreamt from this decision (``target``, ``steer``) on at temperature 0, within the grip
        envelope (``control.brake_ahead`` at ``anticipate`` units/s a decision); else none."""
        if self.anticipate is None:
            return np.inf
        steers, h = [steer], self.h
        for _ in range(ANTICIPATE_HORIZON - 1):
            z, h = self.sim.transition(z, h, np.array([speed, steer], np.float32))
            speed = float(speed_after(speed, target))
            target, steer = self.choose(z, h)
            steers.append(steer)
        return brake_ahead(np.clip(steers, -1.0, 1.0), self.anticipate)

    def choose(self, z: np.ndarray, h: np.ndarray) -> tuple:
        if self.controller is None:
            return super().choose(z, h)
        f = self.controller.features(z[None], h[None])
        clone = self.sim.act(z, h)[None] if self.controller.base == "cloned" else None
        target, steer = self.controller.decide(f, clone)
        return float(target[0]), float(steer[0])

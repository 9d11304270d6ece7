"""``MPCAgent`` ("mpc"): model-predictive path integral control (MPPI) in the dream, seeded by
the policy and scored by the learned reward and value heads.

At each decision it encodes the view and keeps the transition's hidden state stepped along
the drive, as ``ClonedAgent`` does. The policy then drives on in the dream for ``horizon``
decisions: its plan is the prior. ``candidates - 1`` perturbed copies of it (steering and target
speed, noise correlated in time) and the prior itself are rolled out in one batch
(``Simulator.rollout_candidates_scored``, ``futures`` sampled futures each where ``futures >
1``), each dream stepped with the speeds the car would reach under its targets
(``control.speeds_reached``: the transition learnt from the speedometer's speed). Each is scored
by the predicted rewards less ``w_off`` times the predicted off-road chance, discounted, plus the
discounted value of the last state. The first action is the policy's, moved by the candidates'
first actions weighted by ``exp(score / (spread * sd))`` less their plain average (so that a
dream that prefers no candidate leaves the policy's action as it is). It is replanned at every
decision. ``departures`` counts the decisions where the applied action left the policy's own by
more than ``DEPART_STEER`` in steering or ``DEPART_SPEED`` in target speed, ``changes`` sums the
differences (target speed, steering) over the ``planned`` decisions.

The planner is a safety net (``guard``): where the dream gives the policy's own plan (the
unperturbed candidate, over its futures) a mean off-road chance below ``guard``, the policy's
action is applied as it is, and the candidates weigh in only where the dream says the policy's
plan leaves the road. ``guarded`` counts the decisions kept so. Without it the candidates' small
moves change a lap the policy drives well into another, and on a few tracks into a spin: on the
100 held-out tracks 17000-17099, ``guard=None`` lost more than 30 points to the policy alone on 5
tracks (down to 275), ``guard=0.05`` on none, and kept the one rescue (``docs/carracing.md``). The
guard is set for the world: 0.1 since the default of 2026-12-02, whose dream is warier of the
policy's own plan, so that the candidates weigh in as often as they did (0.8 % of the decisions
on tracks 6000-6031; ``python -m drivesim.carracing.guard`` measures it for a weight file).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .. import _checks
from .._drivesim import Model, Simulator
from .bearings import bearings_option
from .cloned import GRIP, PACE, grip_option, pace_option, paced_control, top_speed, traction_option
from .control import SPEED_MAX, ModelAgent, brake_ahead, speed_after, speeds_reached

#: A decision departs from the policy when its steering differs by more than this...
DEPART_STEER = 0.05
#: ...or its target speed by more than this (Box2D units/s).
DEPART_SPEED = 2.0


class MPCAgent(ModelAgent):
    """MPPI seeded by the policy, scored by the reward and value heads (see the module).
    ``act(frame, speed)`` takes the models' view (``observe(env)``, ``(80, 160, 3)`` uint8) and
    the speedometer, and returns CarRacing's action ``[steer, gas, brake]`` (float32).

    The model needs its policy, reward and value heads and a discount (ValueError otherwise).
    Deterministic for a ``seed``: the noise is drawn from a generator seeded at every
    ``reset()``, and the simulator gives the same bits whatever the thread count.

    The defaults were chosen on tracks 6000-6031 (``docs/planning.md``): 16 candidates, each
    over 4 futures sampled at temperature 1, 8 decisions ahead.

    Options (ValueError outside these, TypeError for the wrong kind): ``candidates`` 2 to 1024;
    ``horizon`` 1 to 100; ``futures`` 1 to 64 (sampled futures per candidate, at sampling
    temperature ``temperature`` > 0; ``futures=1, temperature=0`` is the mean dream, for a
    model that does not sample; ``candidates * futures`` at most 1024); ``threads`` >= 1;
    ``seed`` >= 0; ``temperature`` 0 to 10; ``steer_noise`` 0 to 10; ``speed_noise`` 0 to
    1000; ``w_off`` 0 to 1e6; ``spread`` above 0, at most 1e6; ``smooth`` from 0 to 0.99 (the noise's correlation from one
    decision to the next); ``max_speed`` the fastest target speed planned, above the model's
    trained minimum and at most ``SPEED_MAX`` (None: the model's trained range, where the
    policy's own targets are clipped too); ``guard`` an off-road chance from 0 to 1 (see the
    module; 0.1, where it trips as often with the default as 0.05 did with the world it was set
    for) or None (always weigh the candidates); ``pace``
    as ``ClonedAgent``'s: the target applied, the policy's or the plan's, goes through the
    cloned driver's pace rule and the gas through its traction rule (so that where the guard keeps
    the policy's action the decision is the cloned driver's; None: the policy's speed); ``grip``
    as ``ClonedAgent``'s (the share of the expert's grip envelope, 0.5 to 2, or None); ``traction``
    as ``ClonedAgent``'s (True or False); ``anticipate`` None, or how fast the car slows, units/s
    a decision (0 to 100): the speed is then never above what lets it slow to the grip envelope
    of each steering the policy's plan in the dream holds ahead (``control.brake_ahead``);
    ``bearings`` as ``ClonedAgent``'s (True or False).
    """

    def __init__(
        self,
        model: Optional[Model] = None,
        threads: int = 1,
        candidates: int = 16,
        horizon: int = 8,
        futures: int = 4,
        temperature: float = 1.0,
        steer_noise: float = 0.08,
        speed_noise: float = 3.0,
        smooth: float = 0.7,
        w_off: float = 5.0,
        spread: float = 2.0,
        seed: int = 0,
        max_speed: Optional[float] = None,
        guard: Optional[float] = 0.1,
        pace: Optional[float] = PACE,
        grip: Optional[float] = GRIP,
        traction: bool = True,
        anticipate: Optional[float] = None,
        bearings: bool = True,
    ):
        count, number = _checks.integer, _checks.number
        self.candidates, self.horizon = count("candidates", candidates, 2, 1024), count("horizon", horizon, 1, 100)
        self.futures, self.seed = count("futures", futures, 1, 64), count("seed", seed, 0)
        # Bounded so that no decision overflows: a dream sampled far past its spread, noise or
        # weights whose scores leave float32.
        self.temperature = number("temperature", temperature, 0.0, 10.0)
        self.steer_noise, self.speed_noise = number("steer_noise", steer_noise, 0.0, 10.0), number("speed_noise", speed_noise, 0.0, 1000.0)
        self.smooth, self.w_off = number("smooth", smooth, 0.0, 0.99), number("w_off", w_off, 0.0, 1e6)
        self.spread = number("spread", spread, 0.0, 1e6, above=True)
        self.guard = None if guard is None else number("guard", guard, 0.0, 1.0)
        self.model = model if model is not None else Model.load()
        self.pace, self.top = pace_option(self.model, pace), top_speed(self.model)
        self.grip, self.traction = grip_option(grip), traction_option(traction, self.pace)
        self.anticipate = None if anticipate is None else number("anticipate", anticipate, 0.0, 100.0)
        self.bearings = bearings_option(bearings)
        missing = [n for n in ("policy", "reward", "value") if getattr(self.model, f"{n}_width") is None]
        if missing or self.model.discount is None:
            raise ValueError(f"mpc needs a model with its policy, reward and value heads and a discount: "
                             f"missing {', '.join(missing) or 'drivesim.discount'} (train them with `train heads`)")
        if self.candidates * self.futures > 1024:
            raise ValueError(f"candidates * futures is {self.candidates * self.futures}: at most 1024 rollouts a decision")
        if self.futures > 1 and self.temperature == 0.0:
            raise ValueError("futures > 1 needs a sampling temperature above 0 (else every future is the mean)")
        if self.temperature > 0.0 and not self.model.samples:
            raise ValueError("temperature > 0 needs a model that samples (Model.samples)")
        batch = self.candidates * self.futures
        self.sim = Simulator(self.model, batch=batch, threads=count("threads", threads, 1))
        specs = self.model.actions
        low, high = (specs[0]["min"], specs[0]["max"]) if specs else (0.0, 100.0)
        if max_speed is not None:
            high = number("max_speed", max_speed, low, SPEED_MAX, above=True)
        self.speed_range = (low, high)
        discount = np.float32(self.model.discount)
        self.weights = discount ** np.arange(self.horizon, dtype=np.float32)  # per step's reward
        self.tail = float(discount**self.horizon)  # the last state's value
        self.reset()

    def reset(self) -> None:
        """Forgets the drive: call at every new episode."""
        self.h = np.zeros(self.model.hidden_dim, np.float32)
        self.decisions = self.planned = self.departures = self.guarded = 0
        self.changes = np.zeros(2)  # summed |plan - policy|: target speed, steering
        self.rng = np.random.default_rng(self.seed)
        self.last_state: Optional[tuple] = None  # (z, h) the last plan started from
        self.last_plan: Optional[np.ndarray] = None  # (horizon, 2) dream actions of the chosen plan
        self.prior_steers: Optional[np.ndarray] = None  # (horizon,) the policy's plan's steering, for anticipate
        self.chance: Optional[float] = None  # the policy's plan's off-road chance at the last plan
        for part in (self.traction, self.bearings):
            if part is not None:
                part.reset()

    def prior(self, z: np.ndarray, h: np.ndarray, speed: float) -> tuple[np.ndarray, np.ndarray]:
        """The policy driving on in the dream from ``(z, h)`` at ``speed``: its target speeds and
        steerings, ``(horizon,)`` each. The dream is stepped with the speed the car would reach
        under ``speed_control`` (``control.speed_after``), not the target itself."""
        targets, steers = np.empty(self.horizon, np.float32), np.empty(self.horizon, np.float32)
        for t in range(self.horizon):
            targets[t], steers[t] = self.sim.act(z, h)
            if t + 1 < self.horizon:
                z, h = self.sim.transition(z, h, np.array([speed, steers[t]], np.float32))
                speed = float(speed_after(speed, targets[t]))
        return targets, steers

    def _noise(self, sd: float) -> np.ndarray:
        """``(candidates, horizon)`` noise of deviation ``sd``, correlated ``smooth`` in time
        (AR(1)); the first candidate's is zero (the prior itself is a candidate)."""
        white = self.rng.standard_normal((self.candidates, self.horizon)).astype(np.float32)
        out = np.empty_like(white)
        out[:, 0] = white[:, 0]
        keep = np.sqrt(1.0 - self.smooth**2)
        for t in range(1, self.horizon):
            out[:, t] = self.smooth * out[:, t - 1] + keep * white[:, t]
        out[0] = 0.0
        return sd * out

    def plan(self, z: np.ndarray, h: np.ndarray, speed: float) -> tuple[float, float, np.ndarray, np.ndarray]:
        """``(steer, target speed, dream actions (horizon, 2) of the weighted plan, the policy's
        first (target, steer))`` for the state ``(z, h)`` at ``speed``."""
        targets, steers = self.prior(z, h, speed)
        self.prior_steers = steers
        # The candidates are left unclipped and their dream actions clipped: a candidate beyond a
        # limit drives as one at the limit, and the weighted mean is not pulled away from a
        # prior at the limit (the policy's target speed often is). The action applied is clipped.
        steer = steers + self._noise(self.steer_noise)  # (K, H)
        target = targets + self._noise(self.speed_noise)
        speed_in = speeds_reached(speed, np.clip(target, *self.speed_range))
        dream = np.stack([np.clip(speed_in, *self.speed_range), np.clip(steer, -1.0, 1.0)], axis=-1)
        actions = dream.transpose(1, 0, 2)  # (H, K, 2) step-major
        actions = np.repeat(actions, self.futures, axis=1).astype(np.float32)  # futures side by side
        self.sim.set_sampling(self.temperature, self.seed * 1_000_003 + self.decisions)
        _, rewards, values = self.sim.rollout_candidates_scored(h, actions, z=z)
        self.chance = float(rewards[:, : self.futures, 1].mean())  # the guard's figure (`guard.py` reads it)
        if self.guard is not None and self.chance < self.guard:
            # The dream keeps the policy's own plan on the road: no reason to depart from it.
            self.guarded += 1
            return float(np.clip(steers[0], -1.0, 1.0)), float(np.clip(targets[0], *self.speed_range)), \
                actions[:, 0], np.array([targets[0], steers[0]])
        gain = rewards[..., 0] - self.w_off * rewards[..., 1]  # (H, K * F)
        score = self.weights @ gain + self.tail * values[-1]
        score = score.reshape(self.candidates, self.futures).mean(axis=1)
        w = np.exp((score - score.max()) / (self.spread * score.std() + 1e-6))
        w /= w.sum()
        # The weights' excess over the uniform average moves the plan from the prior: where the
        # dream prefers no candidate, the policy's own action is applied, not the noise's mean.
        excess = w - 1.0 / self.candidates
        first_target = float(np.clip(targets[0] + excess @ (target[:, 0] - targets[0]), *self.speed_range))
        first_steer = float(np.clip(steers[0] + excess @ (steer[:, 0] - steers[0]), -1.0, 1.0))
        plan = np.einsum("k,hkc->hc", w, actions[:, :: self.futures])
        return first_steer, first_target, plan, np.array([targets[0], steers[0]])

    def drive(self, frame: np.ndarray, z: np.ndarray, speed: float) -> np.ndarray:
        steer, target, plan, policy = self.plan(z, self.h, speed)
        self.planned += 1
        change = np.abs([target - policy[0], steer - policy[1]])
        self.changes += change
        self.departures += bool(change[1] > DEPART_STEER or change[0] > DEPART_SPEED)
        # The target, the policy's or the plan's, through the cloned driver's pace rule: where the
        # guard keeps the policy's action, the decision is the cloned driver's.
        limit = np.inf
        if self.anticipate is not None:  # slow before the bends the policy's plan steers into
            limit = brake_ahead(np.clip(self.prior_steers, -1.0, 1.0), self.anticipate, self.grip or 1.0)
        gas, brake = paced_control(self.sim, z, self.h, speed, target, steer, self.top, self.pace, self.grip,
                                   self.traction, limit)
        self.last_state, self.last_plan = (z, self.h), plan
        _, self.h = self.sim.transition(z, self.h, np.array([speed, steer], np.float32))
        return np.array([steer, gas, brake], np.float32)

    def imagine(self) -> Optional[np.ndarray]:
        """The mean dream of the last weighted plan: ``(horizon, 80, 160, 3)`` uint8 frames (for
        pictures, not for driving)."""
        if self.last_plan is None:
            return None
        z, h = self.last_state
        self.sim.set_sampling(0.0, 0)
        _, frames = self.sim.rollout_candidates(h, self.last_plan[:, None, :].astype(np.float32), z=z, frames=True)
        return frames[:, 0]

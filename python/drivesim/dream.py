"""The dream as gymnasium environments: ``DreamEnv`` (one drive) and ``DreamVectorEnv`` (N
drives stepped in one batch by the crate's ``Environment``), registered as
``drivesim/Dream-v0``.

A drive starts from real seed frames (the built-in seed clip, an episodes file, or frames
given to ``reset``), then every step the transition predicts the next code under the action and
the generator draws it: the observation is that 8-bit frame, ``(80, 160, 3)``. The action is
``(speed, steering)`` within the ranges the model was trained on (``action_bounds``); actions
outside are clipped. The reward is the distance driven on the road this step (speed / frame
rate, times the share of the car's width over road), less a penalty for being off the road's
centre (the near offset over half the frame's width), both read from the code by a
``RoadCost``. Episodes are truncated after ``max_steps`` steps.

Options for a learner trained in the dream as it would be in CarRacing (``DreamEnv``; the
vector env takes the first two):

- ``reward="learned"``: the model's reward head instead, the env's reward it expects for the
  decision (CarRacing's scale), read from the state the step reached; ``info["off_road"]`` is
  the head's chance that the car is off the road there.
- ``actions="carracing"``: CarRacing's action space, ``(steer, gas, brake)`` in ``[-1, 1] x
  [0, 1] x [0, 1]``. The dream is stepped with the steering and the car's speed, which moves as
  ``carracing.control.speed_after`` says the car answers the gas and brake that
  ``speed_control`` would give for some target (from the last seed action's speed;
  ``info["speed"]``); with both pressed, the brake.
- ``off_road_steps=N``: the episode terminates once the car has been off the road for ``N``
  steps in a row (the off-road chance above one half: the reward head's, or one less the road's
  share under the car by the ``RoadCost``).
"""

from __future__ import annotations

import os
from typing import Any, Optional, Sequence, Union

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from . import _checks
from ._drivesim import Environment, Model, Simulator, load_episodes
from .road import RoadCost

ModelLike = Union[Model, str, os.PathLike, None]


def action_bounds(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` of ``(speed, steering)``: the ranges in the model's ``drivesim.actions``
    metadata (what it was trained on), or speed 0-100 and steering -1 to 1 without it."""
    specs = model.actions
    if not specs:
        return np.array([0.0, -1.0], np.float32), np.array([100.0, 1.0], np.float32)
    return (np.array([s["min"] for s in specs], np.float32), np.array([s["max"] for s in specs], np.float32))


#: CarRacing's action space: steer, gas, brake.
CARRACING_LOW, CARRACING_HIGH = np.array([-1.0, 0.0, 0.0], np.float32), np.array([1.0, 1.0, 1.0], np.float32)


class _Dream:
    """What both environments share: the model, the seed episodes, the spaces, the reward."""

    def _setup(self, model: ModelLike, episodes, seeds: int, max_steps: int, cost: Optional[RoadCost],
               reward: str = "road", actions: str = "drive", off_road_steps: Optional[int] = None, drives: int = 1):
        default = model is None
        seeds, max_steps = _checks.integer("seeds", seeds, 1), _checks.integer("max_steps", max_steps, 1)
        self.reward_kind = _choice("reward", reward, ("road", "learned"))
        self.actions_kind = _choice("actions", actions, ("drive", "carracing"))
        self.off_road_steps = None if off_road_steps is None else _checks.integer("off_road_steps", off_road_steps, 1)
        self.model = model if isinstance(model, Model) else Model.load(model)
        if self.reward_kind == "learned" and self.model.reward_width is None:
            raise ValueError("reward='learned': the model has no reward head (Model.reward_width is None)")
        self.seeds, self.max_steps = seeds, max_steps
        if episodes is None or isinstance(episodes, (str, os.PathLike)):
            episodes = load_episodes(episodes)
        self.episodes = [(f, a) for f, a in episodes if len(f) >= seeds]
        if not self.episodes:
            raise ValueError(f"no episode has the {seeds} frames a reset needs")
        h, w, c = self.model.frame_shape
        if self.episodes[0][0].shape[1:] != (h, w, c):
            raise ValueError(f"episodes: frames {self.episodes[0][0].shape[1:]}, the model takes {(h, w, c)}")
        self.cost = cost if cost is not None else (RoadCost.default() if default else None)
        if self.cost is None and self.reward_kind == "road":
            raise ValueError("a model other than the default needs its RoadCost (cost=RoadCost.fit(...)) or reward='learned'")
        self.hz = self.model.frame_hz or 12.5
        self.low, self.high = action_bounds(self.model)
        self.frame_space = spaces.Box(0, 255, (h, w, c), np.uint8)
        self.move_space = (
            spaces.Box(CARRACING_LOW, CARRACING_HIGH, (3,), np.float32)
            if self.actions_kind == "carracing"
            else spaces.Box(self.low, self.high, (2,), np.float32)
        )
        self._heads = Simulator(self.model, batch=drives) if self.reward_kind == "learned" else None
        self._speed = np.zeros(0, np.float32)
        self._off_for = np.zeros(0, np.int64)

    def _started(self, actions: np.ndarray, drives: int):
        """After a reset with seed ``actions`` ``(S - 1, drives, 2)``: the speed to start from
        (the last seed action's, clipped to the model's range) and no step off the road yet."""
        last = actions[-1, :, 0] if len(actions) else np.zeros(drives, np.float32)
        self._speed = np.clip(last, self.low[0], self.high[0]).astype(np.float32)
        self._off_for = np.zeros(drives, np.int64)

    def _seed_clip(self, rng: np.random.Generator, options: Optional[dict]):
        """Seed frames ``(S, H, W, 3)`` and the actions between them ``(S - 1, 2)``: from
        ``options`` (``frames`` and ``actions``, or ``episode`` and ``start``), else a random
        episode and start drawn from ``rng``."""
        options = _options(options)
        if "frames" in options:
            return self._given(options, ())
        e = options.get("episode")
        e = int(rng.integers(len(self.episodes))) if e is None else _checks.integer("episode", e, 0)
        if not 0 <= e < len(self.episodes):
            raise ValueError(f"episode {e}: there are {len(self.episodes)}")
        frames, actions = self.episodes[e]
        start = options.get("start")
        start = int(rng.integers(len(frames) - self.seeds + 1)) if start is None else _checks.integer("start", start, 0)
        if not 0 <= start <= len(frames) - self.seeds:
            raise ValueError(f"start {start}: episode {e} has {len(frames)} frames, {self.seeds} seeds")
        return frames[start : start + self.seeds], actions[start : start + self.seeds - 1]

    def _given(self, options: dict, drives: tuple) -> tuple[np.ndarray, np.ndarray]:
        """``options["frames"]`` ``(S, *drives, H, W, 3)`` (uint8, or float32 in [-1, 1]) and
        ``options["actions"]`` ``(S - 1, *drives, 2)`` (zeros when not given), checked."""
        frames = np.asarray(options["frames"])
        h, w, c = self.frame_space.shape
        form = ", ".join(["S", *("N" for _ in drives), str(h), str(w), str(c)])
        if frames.dtype not in (np.uint8, np.float32) or frames.shape[1:] != (*drives, h, w, c) or len(frames) < 1:
            raise ValueError(f"options['frames']: expected uint8 or float32 frames ({form}) with S >= 1, got {frames.dtype} {frames.shape}")
        between = (len(frames) - 1, *drives, 2)
        actions = _checks.floats("options['actions']", options.get("actions", np.zeros(between)), np.float32)
        if actions.shape != between:
            raise ValueError(f"options['actions']: expected shape {between} for {len(frames)} seed frames, got {actions.shape}")
        return frames, actions

    def _clip(self, actions: np.ndarray, drives: tuple) -> np.ndarray:
        """The actions checked (shape ``(*drives, 2)``, or 3 in CarRacing's space), clipped to
        the space, as the ``(speed, steering)`` the dream steps with ``(N, 2)``."""
        shape = (*drives, self.move_space.shape[0])
        a = _checks.floats("action", actions, np.float32)
        if a.shape != shape:
            raise ValueError(f"action: expected shape {shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: not finite: {a}")
        a = np.clip(a, self.move_space.low, self.move_space.high).reshape(-1, shape[-1])
        if self.actions_kind == "drive":
            self._speed = a[:, 0].copy()
            return np.ascontiguousarray(a)
        from .carracing.control import speed_after

        steer, gas, brake = a.T
        # The target that speed_control answers with this gas or brake (0.06 per unit of the gap,
        # braking past its dead band of 4), then the speed the car reaches in the decision. The
        # brake wins where both are pressed, as on the real car (from 0 for 100 frames at gas 0.6:
        # 72 units/s without the brake, 37.5 with 0.1 of it, 4.9 with 0.3).
        now = self._speed
        target = np.where(brake > 0, now - 4.0 - brake / 0.06, np.where(gas > 0, now + gas / 0.06, now))
        moves = np.stack([now, np.clip(steer, self.low[1], self.high[1])], 1).astype(np.float32)
        self._speed = np.clip(speed_after(now, np.maximum(target, 0.0)), self.low[0], self.high[0]).astype(np.float32)
        return np.ascontiguousarray(moves)

    def _reward(self, codes: np.ndarray, hidden: np.ndarray, moves: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """Each drive's reward for the step that reached ``codes`` and ``hidden`` with
        ``moves``, whether it ends the episode, and the step's info."""
        if self.reward_kind == "learned":
            head = self._heads.reward(codes, hidden)
            reward, off_road = head[:, 0].astype(np.float64), np.clip(head[:, 1], 0.0, 1.0)
            info = {"off_road": off_road}
        else:
            road = self.cost.predict(codes)
            on_road = np.clip(road[:, 3], 0.0, 1.0)
            half_width = self.frame_space.shape[1] / 2
            reward = (moves[:, 0] / self.hz * on_road - np.abs(road[:, 0]) / half_width).astype(np.float64)
            off_road, info = 1.0 - on_road, {"road": road}
        if self.actions_kind == "carracing":
            info["speed"] = self._speed.copy()
        self._off_for = np.where(off_road > 0.5, self._off_for + 1, 0)
        ended = self._off_for >= self.off_road_steps if self.off_road_steps else np.zeros(len(codes), bool)
        return reward, ended, info


class DreamEnv(_Dream, gymnasium.Env):
    """One drive in the dream, as a gymnasium environment (``drivesim/Dream-v0``).

    ``model``: a ``Model``, a weight file, or None for the default; ``episodes``: where resets
    take their seed frames (a list of ``(frames, actions)``, an episodes file, or None for the
    built-in seed clip); ``seeds``: real frames before the dream starts; ``max_steps``: steps
    before truncation; ``cost``: the ``RoadCost`` the reward reads (the default model's when
    None); ``reward``, ``actions`` and ``off_road_steps``: see the module (a learner's options:
    the reward head, CarRacing's actions, an end off the road). ``reset(seed=, options=)`` takes ``{"frames": (S, H, W, 3), "actions": (S - 1, 2)}``
    or ``{"episode": i, "start": t}``; without options a seeded random episode and start.

    >>> import gymnasium, drivesim
    >>> env = gymnasium.make("drivesim/Dream-v0")
    >>> obs, info = env.reset(seed=0)
    >>> obs.shape, obs.dtype
    ((80, 160, 3), dtype('uint8'))
    >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

    As CarRacing to a learner, with the model's own reward and an end off the road:

    >>> import numpy as np
    >>> env = drivesim.DreamEnv(reward="learned", actions="carracing", off_road_steps=10)
    >>> env.action_space.shape
    (3,)
    >>> obs, info = env.reset(seed=0)
    >>> obs, reward, terminated, truncated, info = env.step(np.array([0.0, 0.5, 0.0], np.float32))
    >>> sorted(info)
    ['code', 'off_road', 'speed']
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 12.5}

    def __init__(
        self,
        model: ModelLike = None,
        episodes: Any = None,
        seeds: int = 5,
        max_steps: int = 200,
        render_mode: Optional[str] = None,
        threads: int = 1,
        cost: Optional[RoadCost] = None,
        reward: str = "road",
        actions: str = "drive",
        off_road_steps: Optional[int] = None,
    ):
        self._setup(model, episodes, seeds, max_steps, cost, reward, actions, off_road_steps)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r}: only 'rgb_array'")
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.hz}
        self.observation_space = self.frame_space
        self.action_space = self.move_space
        self._env = Environment(self.model, drives=1, candidates=1, threads=threads)
        self._frame: Optional[np.ndarray] = None
        self._t = 0

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """``seed``: None or an integer >= 0 (``np.int64`` too); ``options``: see the class.
        ValueError for a seed, an option or seed frames out of range, TypeError for the wrong
        kind of value."""
        super().reset(seed=_checks.seed(seed))
        frames, actions = self._seed_clip(self.np_random, options)
        self._frame = None  # until the reset succeeds: `step` then raises ResetNeeded
        actions = np.ascontiguousarray(actions[:, None], np.float32)
        self._env.reset(np.ascontiguousarray(frames[:, None]), actions)
        self._started(actions, 1)
        self._frame = self._env.frames()[0]
        self._t = 0
        return self._frame, {"code": self._env.codes[0]}

    def step(self, action):
        if self._frame is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        moves = self._clip(action, ())
        self._env.step(moves)
        self._t += 1
        codes = self._env.codes
        reward, ended, info = self._reward(codes, self._env.hidden, moves)
        self._frame = self._env.frames()[0]
        info = {"code": codes[0], **{k: v[0] for k, v in info.items()}}
        return self._frame, float(reward[0]), bool(ended[0]), self._t >= self.max_steps, info

    def render(self):
        """The current dreamed frame, ``(80, 160, 3)`` uint8 (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array":
            return None
        return None if self._frame is None else self._frame.copy()


class DreamVectorEnv(_Dream, gymnasium.vector.VectorEnv):
    """``num_envs`` drives in the dream stepped in one batch (one pass over the weights for
    all). The arguments are ``DreamEnv``'s. Every drive is truncated at the same step (the dream
    has no crash), so the autoreset mode is ``NEXT_STEP`` and all drives reset together: the
    step after the one that returned ``truncated`` starts every drive from new seed frames and
    returns zero rewards. ``reset(options=)`` takes per-drive ``frames`` ``(S, N, H, W, 3)`` and
    ``actions`` ``(S - 1, N, 2)``. ``reward`` and ``actions`` as ``DreamEnv``'s; an end off the
    road would need each drive reset on its own, which the batch cannot: a learner that wants
    ``off_road_steps`` takes gymnasium's (or its library's) vector of ``DreamEnv``.

    >>> import numpy as np, drivesim
    >>> envs = drivesim.DreamVectorEnv(4)
    >>> obs, info = envs.reset(seed=0)
    >>> obs.shape
    (4, 80, 160, 3)
    >>> obs, rewards, terminated, truncated, info = envs.step(envs.action_space.sample())
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "render_fps": 12.5,
        "autoreset_mode": gymnasium.vector.AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        num_envs: int,
        model: ModelLike = None,
        episodes: Any = None,
        seeds: int = 5,
        max_steps: int = 200,
        render_mode: Optional[str] = None,
        threads: int = 1,
        cost: Optional[RoadCost] = None,
        reward: str = "road",
        actions: str = "drive",
    ):
        num_envs = _checks.integer("num_envs", num_envs, 1)
        self._setup(model, episodes, seeds, max_steps, cost, reward, actions, drives=num_envs)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r}: only 'rgb_array'")
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.hz}
        self.single_observation_space = self.frame_space
        self.single_action_space = self.move_space
        self.observation_space = batch_space(self.frame_space, num_envs)
        self.action_space = batch_space(self.move_space, num_envs)
        self._env = Environment(self.model, drives=num_envs, candidates=1, threads=threads)
        self._frames: Optional[np.ndarray] = None
        self._t = 0
        self._needs_reset = False

    def reset(self, *, seed: Optional[Union[int, Sequence[int]]] = None, options: Optional[dict] = None):
        """``seed``: None, an integer >= 0 (``np.int64`` too), or a non-empty sequence of them
        (one per drive, as gymnasium's vector environments take; the first seeds the draw of
        every drive's start). ValueError for a seed out of range or an empty sequence,
        TypeError for the wrong kind of value; ``options`` as ``DreamEnv.reset``'s, per drive."""
        if seed is not None:
            if not isinstance(seed, (str, bytes)) and isinstance(seed, (Sequence, np.ndarray)):
                if len(seed) == 0:
                    raise ValueError("seed: an empty sequence (give an integer, or one per drive)")
                seed = seed[0]
            seed = _checks.seed(seed)
            self._np_random, self._np_random_seed = gymnasium.utils.seeding.np_random(seed)
        options = _options(options)
        if "frames" in options:
            frames, actions = self._given(options, (self.num_envs,))
        else:
            clips = [self._seed_clip(self.np_random, None) for _ in range(self.num_envs)]
            frames = np.stack([f for f, _ in clips], axis=1)
            actions = np.stack([a for _, a in clips], axis=1)
        self._frames = None  # until the reset succeeds: `step` then raises ResetNeeded
        actions = np.ascontiguousarray(actions, np.float32)
        self._env.reset(np.ascontiguousarray(frames), actions)
        self._started(actions, self.num_envs)
        self._frames = self._env.frames()
        self._t, self._needs_reset = 0, False
        return self._frames, {}

    def step(self, actions):
        if self._frames is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        n = self.num_envs
        if self._needs_reset:
            obs, _ = self.reset()
            return obs, np.zeros(n), np.zeros(n, bool), np.zeros(n, bool), {}
        moves = self._clip(actions, (n,))
        self._env.step(moves)
        self._t += 1
        reward, _, info = self._reward(self._env.codes, self._env.hidden, moves)
        self._frames = self._env.frames()
        self._needs_reset = self._t >= self.max_steps
        truncated = np.full(n, self._needs_reset)
        return self._frames, reward, np.zeros(n, bool), truncated, info

    def render(self):
        """The drives' current frames, ``(num_envs, 80, 160, 3)`` uint8."""
        if self.render_mode != "rgb_array" or self._frames is None:
            return None
        return self._frames.copy()


def _choice(name: str, value: Any, choices: tuple) -> str:
    """``value`` if it is one of ``choices`` (ValueError otherwise)."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


def _options(options: Any) -> dict:
    """A reset's ``options``: None or a dict (TypeError otherwise)."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise TypeError(f"options: expected a dict, got {type(options).__name__}")
    return options

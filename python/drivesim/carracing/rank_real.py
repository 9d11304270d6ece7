"""The rank probe's real side (``python -m drivesim.carracing.rank``): a driver's whole drive of
a track, and (``--windows``) every driver driven in gymnasium's CarRacing from the same starts,
for the same horizon, as in the dream.

The dream rolls each driver ``--horizon`` decisions from states of the unchanged driver's real
drive. A whole real drive is another experiment: a driver that leaves the road at the first
sharp bend is on the grass for most of its lap, while a window of the dream may hold no such
bend. Here the real car is put where the dream starts: the track is reset and the behaviour
drive's actions replayed up to the start (CarRacing is deterministic: the same actions from the
same seed give the same car, frame for frame, which the tests check), the driver takes over
with the behaviour drive's hidden state there, and drives ``horizon`` decisions. Each window
gives the env's reward summed and the share of its decisions with no wheel on the road; its
steering noise is seeded as the dream's row for the same driver and start. A folder's real drives
are one family's: `check_drivers` keeps `drivers_fingerprint` of the drivers that drove them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os

import numpy as np

from .._drivesim import Model, Simulator
from .._files import atomic_write
from .family import ChangedAgent
from .rank_dream import dream_row_seed, window_starts
from .record import decision, wheel_on_road
from .view import observe, speed, unseen


_model = None  # this process's model, loaded at its first job


def process_model(weights):
    """This process's model of ``weights`` (loaded once: the jobs of a run share one file)."""
    global _model
    if _model is None:
        _model = Model.load(weights)
    return _model


def drive_name(args, index: int, seed: int) -> str:
    """The file of driver ``index``'s drive of track ``seed`` in ``--out``: the family's name
    first (families share ``--out`` and the behaviour drive), but for the full family, whose
    runs kept these names before there were others."""
    return f"{'' if args.family_name == 'all' else args.family_name + '_'}{index}_{seed}.json"


def drive_real(agent, seed: int, frames: int, keep_states: bool) -> tuple[dict, list, dict]:
    """One real drive: its figures; (``keep_states``) every decision after the warm-up in order,
    ``(z, h, speed, steering applied)``: the code seen, the driver's hidden state before the
    decision, the speedometer and what the transition was stepped with; and every decision's
    ``actions`` (the env's), ``rewards`` and ``off`` (no wheel on the road), warm-up included:
    what ``replay`` replays and its tests check against."""
    import gymnasium

    env = gymnasium.make("CarRacing-v3", max_episode_steps=frames)
    env.reset(seed=seed)
    agent.reset()
    total, states, done = 0.0, [], False
    trace = {"actions": [], "rewards": [], "off": []}
    while not done:
        action = agent.act(observe(env), speed(env))
        if keep_states and agent.decisions > agent.warmup:
            z, h, v = agent.last_state
            states.append((z.copy(), h.copy(), v, float(action[0])))
        trace["off"].append(not wheel_on_road(env.unwrapped.car))
        reward, _, done = decision(env, action, agent.frame_skip)
        total += reward
        trace["actions"].append(action)
        trace["rewards"].append(reward)
    env.close()
    decisions = len(trace["off"])
    figures = {"reward": round(total, 2), "off_road": round(sum(trace["off"]) / decisions, 4), "decisions": decisions}
    return figures, states, {k: np.array(v, np.float32) for k, v in trace.items()}


def replay(env, actions: np.ndarray, frame_skip: int) -> None:
    """Steps the env, just reset, through ``actions`` (one a decision, ``(D, 3)``), drawing only
    the last decision's last frame (what ``observe`` reads next)."""
    for i, action in enumerate(actions):
        with unseen(env) if i + 1 < len(actions) else contextlib.nullcontext():
            decision(env, action, frame_skip)


def drive_window(env, agent, h: np.ndarray, decisions: int, horizon: int,
                 frames: list | None = None) -> tuple[list, list, list]:
    """``agent`` (a ``family.ChangedAgent``, just reset) takes over the env ``decisions`` decisions
    into the drive with hidden state ``h`` and drives ``horizon`` decisions (fewer where the
    episode ends): each decision's reward, whether the car was off the road as it decided, and
    the transition's input (the speed and the steering applied: what the dream is given to
    replay the window open loop); ``frames``, where given, receives each frame the agent read."""
    agent.decisions, agent.h = decisions, np.array(h, np.float32)  # past the warm-up, the drive's memory
    rewards, off, actions = [], [], []
    for _ in range(horizon):
        now = speed(env)
        frame = observe(env)
        if frames is not None:
            frames.append(frame)
        action = agent.act(frame, now)
        off.append(not wheel_on_road(env.unwrapped.car))
        actions.append([round(float(now), 4), round(float(action[0]), 4)])
        reward, _, done = decision(env, action, agent.frame_skip)
        rewards.append(reward)
        if done:
            break
    return rewards, off, actions


def drive_windows(drive: dict, driver, index: int, seed: int, args, frames: bool = False) -> list:
    """``driver`` (family index ``index``) from each of the behaviour drive's starts on track
    ``seed`` (`rank_dream.window_starts`), with the dream row's noise seed: each window's rewards,
    off-road flags and inputs (`drive_window`), and with ``frames`` the frames it read (else None)."""
    import gymnasium

    starts, at = window_starts(drive, args.starts, args.horizon)
    agent = ChangedAgent(driver, seed=0, model=process_model(args.weights))
    env = gymnasium.make("CarRacing-v3", max_episode_steps=args.frames)
    out = []
    for j, (start, t) in enumerate(zip(starts, at)):
        agent.seed = dream_row_seed(seed, index, j, len(starts))
        agent.reset()
        env.reset(seed=seed)
        replay(env, drive["actions"][:start], agent.frame_skip)
        seen = [] if frames else None
        out.append((*drive_window(env, agent, drive["h"][t], start, args.horizon, seen), seen))
    env.close()
    return out


def windows_dir(args) -> str:
    """Where the windows of ``args.horizon`` and ``args.starts`` are kept (``--out``'s)."""
    return os.path.join(args.out, f"windows_{args.horizon}x{args.starts}")


def window_job(job) -> dict:
    """One driver's windows on one track (`rank_dream.window_starts`): their returns, off-road shares,
    each decision's off-road flag and the transition's input, read from ``--out`` when an earlier
    run drove them (one from before the flags and inputs were kept is driven again)."""
    args, index, seed = job
    path = os.path.join(windows_dir(args), drive_name(args, index, seed))
    if os.path.exists(path):
        with open(path) as f:
            kept = json.load(f)
        if "actions" in kept:
            return kept
    with np.load(os.path.join(args.out, f"drive_{seed}.npz")) as f:
        drive = {k: f[k] for k in f.files}
    returns, off_road, flags, inputs = [], [], [], []
    for rewards, off, actions, _ in drive_windows(drive, args.family[index], index, seed, args):
        returns.append(float(np.sum(rewards)))
        off_road.append(float(np.mean(off)))
        flags.append([int(o) for o in off])
        inputs.append(actions)
    out = {"driver": index, "seed": seed, "return": returns, "off_road": off_road, "off": flags, "actions": inputs}
    with atomic_write(path) as f:
        f.write(json.dumps(out).encode())
    return out


def padded_to_horizon(windows: list, horizon: int) -> np.ndarray:
    """A real window's off-road flags (or inputs), ``(windows, horizon, ...)``: a window the
    episode's end cut short keeps its last to the horizon (the car stays where it ended)."""
    return np.array([w + w[-1:] * (horizon - len(w)) for w in windows], float)


def drivers_fingerprint(model: Model) -> str:
    """A hash of what the drivers of ``model`` answer to fixed inputs (their policy and pace, and
    their transition's step): the same for the same drivers, whatever the thread count, and for
    the built-in default, which has no file to hash."""
    sim, rng = Simulator(model), np.random.default_rng(0)
    z = rng.standard_normal((1, model.z_dim)).astype(np.float32)
    h = np.tanh(rng.standard_normal((1, model.hidden_dim))).astype(np.float32)
    answers = [sim.act(z, h), *sim.transition(z[0], h[0], np.array([30.0, 0.1], np.float32))]
    if model.pace_width is not None:
        answers.append(sim.pace(z, h))
    return hashlib.sha256(b"".join(np.asarray(a, np.float32).tobytes() for a in answers)).hexdigest()


def check_drivers(out: str, fingerprint: str) -> None:
    """Keeps ``fingerprint`` in ``out/drivers.json``, or raises ValueError where the folder
    holds another drivers' real drives."""
    path = os.path.join(out, "drivers.json")
    if os.path.exists(path):
        with open(path) as f:
            kept = json.load(f).get("fingerprint")
        if kept != fingerprint:
            raise ValueError(f"{out} holds the real drives of other drivers (another --weights, or another "
                             f"built-in default): give another --out")
        return
    with atomic_write(path) as f:
        f.write(json.dumps({"fingerprint": fingerprint}).encode())

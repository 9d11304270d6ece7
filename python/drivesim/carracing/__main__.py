"""Scores an agent on gymnasium's CarRacing-v3 with the env's own reward.

  python -m drivesim.carracing --agent mpc --seeds 0-19 --out runs/mpc

Per track: the env's reward over its 1000 frames (less if the lap ends), the frames driven,
the share of the track's tiles visited, the share of decisions with a wheel on the road, and
the milliseconds the agent took per decision; then the mean and standard deviation. For a
planner seeded by the policy (``mpc``), also the share of decisions where the plan departed
from the policy's own action (and, in the JSON, the mean change of target speed and steering),
and the score of the policy alone (``cloned``, the same model) on the same track, with the
paired difference and its standard error: what planning adds. With
``--out``, each track's figures go to ``DIR/track_SEED.json`` (a run that stops resumes: tracks
already there are read, not driven again) and an animation ``DIR/track_SEED.gif`` of the real
frames beside what the agent imagined at each decision, dreamed 2 and 8 steps ahead (``mpc``:
its chosen plan; ``cloned``: its policy driving on in the dream). ``--no-gif`` keeps the figures
and the resuming without the animation, whose dreaming and drawing at every decision make a
drive three to four times slower (100 tracks of ``dreamt`` on 2 cores: 17.5 minutes, 5 without).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import sys
import time

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame draws off-screen
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np

from .._files import atomic_write
from .agents import AGENTS, make_agent
from .view import decision_steps, observe, parse_seeds, speed


def drive(agent, seed: int, frames: int = 1000, pictures: bool = False) -> tuple[dict, list]:
    """One track: the figures, and (with ``pictures``) a row of frames per decision."""
    import gymnasium

    env = gymnasium.make("CarRacing-v3", max_episode_steps=frames)
    env.reset(seed=seed)
    agent.reset()
    car = env.unwrapped
    total, steps, decisions, on_road, seconds, rows = 0.0, 0, 0, 0, 0.0, []
    action, done = np.zeros(3, np.float32), False
    while not done:
        view, now = observe(env), speed(env)
        start = time.perf_counter()
        action = agent.act(view, now)
        seconds += time.perf_counter() - start
        decisions += 1
        on_road += any(len(w.tiles) > 0 for w in car.car.wheels)
        if pictures:
            rows.append(picture_row(agent, view))
        for _, reward, terminated, truncated, _ in decision_steps(env, action, agent.frame_skip):
            total += float(reward)
            steps += 1
            if terminated or truncated:
                done = True
                break
    figures = {
        "seed": seed,
        "reward": round(total, 2),
        "frames": steps,
        "tiles": round(car.tile_visited_count / len(car.track), 4),
        "on_road": round(on_road / decisions, 4),
        "ms_per_decision": round(1000 * seconds / decisions, 3),
    }
    if getattr(agent, "bearings", None) is not None:
        figures["turns"] = agent.bearings.turns
    if hasattr(agent, "departures"):  # a planner seeded by the policy
        figures["departed"] = round(agent.departures / max(agent.planned, 1), 4)
        speed_change, steer_change = agent.changes / max(agent.planned, 1)
        figures["speed_change"], figures["steer_change"] = round(float(speed_change), 3), round(float(steer_change), 4)
    env.close()
    return figures, rows


def picture_row(agent, view: np.ndarray) -> np.ndarray:
    """The real frame beside what the agent imagined (``agent.imagine()``), 2 steps and its
    last step ahead."""
    dream = agent.imagine() if hasattr(agent, "imagine") else None
    blank = np.zeros_like(view)
    if dream is None:
        return np.concatenate([view, blank, blank], axis=1)
    return np.concatenate([view, dream[min(1, len(dream) - 1)], dream[-1]], axis=1)


def write_gif(path: str, rows: list, fps: float) -> None:
    from PIL import Image

    images = [Image.fromarray(r).resize((r.shape[1] * 2, r.shape[0] * 2), Image.NEAREST) for r in rows]
    with atomic_write(path) as f:
        images[0].save(f, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


_agent = None  # the agent of this process, made at its first track
_policy = None  # the policy alone (cloned) of this process, for a planner's comparison


def track(job) -> dict:
    """One track's figures: read from ``--out`` when a previous run drove it, else driven."""
    global _agent
    args, seed = job
    path = os.path.join(args.out, f"track_{seed}.json") if args.out else None
    if path and os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    global _policy
    if _agent is None:
        _agent = make_agent(args.agent, weights=args.weights, threads=args.threads, **dict(args.set))
    gif = bool(args.out) and not args.no_gif
    r, rows = drive(_agent, seed, args.frames, pictures=gif)
    if "departed" in r and not args.no_policy_alone:
        if _policy is None:
            # the policy the planner departs from, at its own speed
            _policy = make_agent("cloned", weights=args.weights, threads=args.threads, pace=None)
        r["policy_alone"] = drive(_policy, seed, args.frames)[0]["reward"]
    if gif:
        write_gif(os.path.join(args.out, f"track_{seed}.gif"), rows, 12.5)
    if args.out:
        with atomic_write(path) as f:
            f.write(json.dumps(r).encode())
    return r


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agent", choices=sorted(AGENTS), default="mpc")
    p.add_argument("--seeds", type=parse_seeds, required=True, help="track seeds, e.g. 0-19")
    p.add_argument("--weights", help="weight file (default: the built-in model)")
    p.add_argument("--threads", type=int, default=1, help="threads per agent")
    p.add_argument("--frames", type=int, default=1000, help="env frames per track (CarRacing-v3: 1000)")
    p.add_argument("--out", help="folder for per-track figures and animations (resumable)")
    p.add_argument("--no-gif", action="store_true",
                   help="with --out: the figures only, no animation (three to four times faster)")
    p.add_argument("--workers", type=int, default=1,
                   help="tracks driven at once, each by its own agent in its own process (the ms per decision "
                        "then include the workers' contention: measure it with 1)")
    p.add_argument("--set", type=option, action="append", default=[], metavar="NAME=VALUE",
                   help="an option of the agent (e.g. --set candidates=64; its class's docstring lists them)")
    p.add_argument("--no-policy-alone", action="store_true",
                   help="for a planner seeded by the policy: do not also drive the policy alone on each track")
    args = p.parse_args(argv)
    global _agent, _policy
    _agent = _policy = None  # a run's agents are its own, even when main is called again in one process
    if args.threads < 1 or args.frames < 1 or args.workers < 1:
        p.error("--threads, --frames and --workers must be positive")
    if args.no_gif and not args.out:
        p.error("--no-gif goes with --out (without --out nothing is written)")
    if args.out:
        os.makedirs(args.out, exist_ok=True)
    jobs = [(args, seed) for seed in args.seeds]
    planner = args.agent == "mpc"
    extra = f" {'departed':>8}" + ("" if args.no_policy_alone else f" {'policy':>8}") if planner else ""
    if args.agent in ("cloned", "mpc") and dict(args.set).get("bearings", True):
        extra = f" {'turns':>5}" + extra
    print(f"{'track':>6} {'reward':>8} {'frames':>6} {'tiles':>6} {'on road':>7} {'ms/decision':>11}{extra}", flush=True)
    results = []
    with multiprocessing.Pool(min(args.workers, len(jobs))) if args.workers > 1 else contextlib.nullcontext() as pool:
        for r in (pool.imap(track, jobs) if pool else map(track, jobs)):
            results.append(r)
            print(f"{r['seed']:>6} {r['reward']:>8.1f} {r['frames']:>6} {r['tiles']:>6.1%} {r['on_road']:>7.1%} "
                  f"{r['ms_per_decision']:>11.2f}" + more_columns(r), flush=True)
    rewards = np.array([r["reward"] for r in results])
    ms = np.array([r["ms_per_decision"] for r in results])
    print(f"{args.agent}: {rewards.mean():.1f} ± {rewards.std():.1f} over {len(rewards)} tracks "
          f"(min {rewards.min():.1f}, max {rewards.max():.1f}); {ms.mean():.2f} ms per decision")
    alone = np.array([r["policy_alone"] for r in results if "policy_alone" in r])
    if len(alone) == len(results):
        diff = rewards - alone
        se = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else float("nan")
        departed = np.mean([r["departed"] for r in results])
        print(f"the policy alone: {alone.mean():.1f} ± {alone.std():.1f}; {args.agent} - policy = {diff.mean():+.1f} "
              f"± {se:.1f} (standard error), ahead on {(diff > 0).sum()} of {len(diff)} tracks; "
              f"departed from the policy at {departed:.1%} of decisions")
    return 0


def option(text: str) -> tuple:
    """``NAME=VALUE`` as ``(name, value)``, the value an int or a float where it reads as one,
    None for ``none`` (an option turned off: ``--set guard=none``)."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    if value.lower() == "none":
        return name, None
    for kind in (int, float):
        try:
            return name, kind(value)
        except ValueError:
            pass
    return name, value


def more_columns(r: dict) -> str:
    """The columns after the common ones: the times the bearings took over (``bearings.Bearings``),
    a planner's departures from the policy and the policy alone's score."""
    out = f" {r['turns']:>5}" if "turns" in r else ""
    out += f" {r['departed']:>8.1%}" if "departed" in r else ""
    return out + (f" {r['policy_alone']:>8.1f}" if "policy_alone" in r else "")


if __name__ == "__main__":
    sys.exit(main())

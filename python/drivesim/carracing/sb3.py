"""A stable-baselines3 learner trained in the dream, unchanged (issue 60): PPO with its stock
CNN policy on ``drivesim/Dream-v0`` as it would train on CarRacing (the dream's frames,
CarRacing's actions, the world model's reward head, an episode ended once the car is off the
road), then driven on the real track. Needs ``pip install stable-baselines3`` (and PyTorch).

  python -m drivesim.carracing.sb3 train --world W --starts E.safetensors.gz --steps 50000 --out ppo.zip
  python -m drivesim.carracing.sb3 score --world W --policy ppo.zip --seeds 16000-16009

``train`` resets every drive from a random recorded state of ``E`` (real CarRacing frames);
``score`` drives each real track as ``python -m drivesim.carracing`` does (the agent's
warm-up, a decision every 4 frames, the env's own reward) and prints the same table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .._drivesim import Model, load_episodes
from .control import check_inputs, warmup_action
from .view import parse_seeds


def _stable_baselines3():
    try:
        import stable_baselines3
    except ImportError:
        raise ImportError("drivesim.carracing.sb3 needs stable-baselines3: pip install stable-baselines3") from None
    return stable_baselines3


class PolicyAgent:
    """A stable-baselines3 policy (trained on ``Dream-v0``'s frames and CarRacing's actions) as
    an agent of the real CarRacing: its deterministic action for the models' view."""

    frame_skip = 4
    warmup = 12

    def __init__(self, policy, frame_shape=(80, 160, 3)):
        self.policy, self.frame_shape = policy, frame_shape
        self.reset()

    def reset(self) -> None:
        self.decisions = 0

    def act(self, frame: np.ndarray, speed: float) -> np.ndarray:
        frame, speed = check_inputs(frame, speed, self.frame_shape)
        warming_up = warmup_action(self, speed)
        if warming_up is not None:
            return warming_up
        action, _ = self.policy.predict(frame, deterministic=True)
        return np.clip(np.asarray(action, np.float32), [-1.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def train(args) -> None:
    sb3 = _stable_baselines3()
    import gymnasium
    from stable_baselines3.common.env_util import make_vec_env

    world = Model.load(args.world)
    starts = load_episodes(args.starts)

    def dream():
        return gymnasium.make("drivesim/Dream-v0", model=world, episodes=starts, reward="learned",
                              actions="carracing", off_road_steps=args.off_road_steps, max_steps=args.max_steps)

    env = make_vec_env(dream, n_envs=args.envs, seed=args.seed)
    ppo = sb3.PPO("CnnPolicy", env, n_steps=128, batch_size=128, n_epochs=4, learning_rate=3e-4, seed=args.seed,
                  verbose=1)
    ppo.learn(total_timesteps=args.steps)
    ppo.save(args.out)


def score(args) -> None:
    sb3 = _stable_baselines3()
    from .__main__ import drive

    agent = PolicyAgent(sb3.PPO.load(args.policy, device="cpu"), Model.load(args.world).frame_shape)
    rewards = []
    print(" track   reward frames  tiles on road")
    for seed in parse_seeds(args.seeds):
        r, _ = drive(agent, seed, args.frames)
        rewards.append(r["reward"])
        print(f"{seed:6d} {r['reward']:8.1f} {r['frames']:6d} {r['tiles']:6.1%} {r['on_road']:7.1%}", flush=True)
    print(f"ppo: {np.mean(rewards):.1f} ± {np.std(rewards):.1f} over {len(rewards)} tracks")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivesim.carracing.sb3", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = p.add_subparsers(dest="command", required=True)
    t = commands.add_parser("train", help="PPO in the dream")
    t.add_argument("--world", type=Path, default=None, help="the world model (default: the built-in)")
    t.add_argument("--starts", type=Path, required=True, help="episodes recorded in real CarRacing")
    t.add_argument("--steps", type=int, default=50_000, help="dream steps PPO learns from")
    t.add_argument("--envs", type=int, default=4, help="dream drives stepped side by side")
    t.add_argument("--max-steps", type=int, default=200, help="decisions a dream drive lasts at most")
    t.add_argument("--off-road-steps", type=int, default=4, help="decisions off the road that end a drive")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--out", type=Path, required=True, help="the policy's file (stable-baselines3's zip)")
    s = commands.add_parser("score", help="the policy on real CarRacing tracks")
    s.add_argument("--world", type=Path, default=None, help="the world model it was trained in")
    s.add_argument("--policy", type=Path, required=True)
    s.add_argument("--seeds", required=True, help="track seeds, e.g. 16000-16009")
    s.add_argument("--frames", type=int, default=1000)
    args = p.parse_args(argv)
    if args.command == "train":
        if min(args.steps, args.envs, args.max_steps, args.off_road_steps) < 1 or args.seed < 0:
            p.error("--steps, --envs, --max-steps and --off-road-steps must be positive, --seed not negative")
        train(args)
    else:
        if args.frames < 1:
            p.error("--frames must be positive")
        score(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())

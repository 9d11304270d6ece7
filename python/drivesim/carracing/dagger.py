"""DAgger: recovery data for the cloned driver, labelled by the expert (Ross et al., 2011).

Round 0 clones the policy on the expert's own episodes (``--data``, recorded by
``python -m drivesim record --driver expert``). Each later round k:

1. the round k-1 policy drives real CarRacing through ``make_agent("cloned", weights=...)``
   and ``observe``, on tracks of its own (``--per-round`` tracks from ``--tracks``);
2. at every decision the expert labels the state the car is in with what it would do there
   (the speed it would drive to and its steering: ``expert.Expert``, which reads the env, not
   the agent), while the agent's own action is the one applied;
3. those frames, with the agent's actions (what its transition was stepped with), the labels
   and the rewards, join the expert's episodes and every earlier round's (mirror images are
   ``train policy``'s own, by default);
4. the policy is cloned again from the base model (``train policy --restart``, fitting labels).

With ``--noise SD`` the rounds' drives perturb the agent's steering (DART, Laskey et al., 2017):
an AR(1) offset of standard deviation SD and correlation ``NOISE_CORRELATION`` per decision, the
same for a track's seed, is added to what the policy asks, so the car drifts off its line the way
a planner's departures take it, and the expert labels the way back. The transition is stepped
with the steering applied, and that is the action recorded.

After each round the policy is scored on ``--heldout`` tracks, never driven in a round
(``python -m drivesim.carracing --agent cloned``), and a line goes to ``DIR/log.jsonl``.
Everything a round makes is written atomically under ``DIR/round_K/``, and a step whose file
exists is not done again: a killed run started again with the same arguments goes on where it
stopped (the evaluation resumes per track). Needs the ``drivesim`` package with CarRacing
(``pip install "./python[carracing]"``) and the trainer (``cargo build --release -p
drivesim-examples --features train --example train``).

  python -m drivesim dagger --data data/expert.safetensors.gz --rounds 4 --tracks 4000-4099 \\
      --per-round 16 --heldout 5000-5019 --dir runs/dagger --workers 2
"""

import argparse
import json
import os
import subprocess
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from .. import _files, episodes
from . import record


# Decision to decision correlation of `--noise`'s steering offset (about 5 decisions, 0.4 s).
NOISE_CORRELATION = 0.8


def steering_noise(sd, seed):
    """`--noise`'s offsets for the track `seed`: an endless AR(1) sequence of standard deviation
    `sd` (all zeros for sd 0)."""
    rng, offset = np.random.default_rng([seed, 0x0DA6]), 0.0
    rho = NOISE_CORRELATION
    while True:
        offset = rho * offset + np.sqrt(1.0 - rho * rho) * sd * rng.standard_normal()
        yield offset


def perturb(agent, action, offset):
    """`action` (the cloned agent's, just taken) with `offset` added to its steering (clipped to
    [-1, 1]), the agent's transition stepped again from its last state with the steering applied."""
    if offset == 0.0 or agent.last_state is None:
        return action
    z, h, speed = agent.last_state
    steer = float(np.clip(action[0] + offset, -1.0, 1.0))
    _, agent.h = agent.sim.transition(z, h, np.array([speed, steer], np.float32))
    return np.array([steer, action[1], action[2]], np.float32)


def drive_labelled(job):
    """One track driven by the cloned agent of `weights` (its steering perturbed by `noise`'s
    offsets, `steering_noise`), labelled by the expert at every decision after the agent's
    warm-up: an `episodes.Episodes` of one episode (None if the drive has no decision past the
    warm-up) and the env's reward over the drive."""
    weights, seed, frames, noise = job
    import gymnasium
    from .. import carracing

    agent = carracing.make_agent("cloned", weights=str(weights), pace=None)  # the policy being learnt drives
    env = gymnasium.make("CarRacing-v3", max_episode_steps=frames)
    env.reset(seed=seed)
    car_env = env.unwrapped
    teacher = record.Driver(car_env.track, None, "expert")
    seconds = agent.frame_skip / record.car_racing.FPS
    offsets = steering_noise(noise, seed)

    def expert_label():
        steering, _, _ = teacher.act(car_env.car, seconds)
        return teacher.target, steering[0]

    out, total = record.drive_agent(env, agent, label=expert_label,
                                    adjust=lambda action: perturb(agent, action, next(offsets)))
    if not out["frames"]:
        return None, total
    return record.one_episode(out, np.array(out["labels"], np.float32)), total


def train(args, data_files, out):
    """The policy cloned from `--base` on `data_files` joined (labels where they have them)."""
    joined = out.with_name("joined.safetensors")
    episodes.write(joined, episodes.Episodes.concat([episodes.read(f) for f in data_files]),
                   {"source": "dagger: the expert's episodes and the labelled rounds", "frame_hz": "12.5"})
    cmd = [str(args.trainer), "policy", "--weights", str(args.base), "--episodes", str(joined),
           "--holdout", str(args.holdout), "--restart", "--threads", str(args.workers), "--steps", str(args.steps),
           "--out", str(out)]
    subprocess.run(cmd, check=True)
    joined.unlink()


def evaluate(args, weights, out_dir):
    """The held-out tracks' figures of the cloned agent of `weights` (resumable per track)."""
    cmd = [sys.executable, "-m", "drivesim.carracing", "--agent", "cloned", "--weights", str(weights),
           "--seeds", args.heldout_text, "--workers", str(args.workers), "--frames", str(args.frames),
           "--out", str(out_dir)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    runs = [json.loads((out_dir / f"track_{s}.json").read_text()) for s in args.heldout]
    return [r["reward"] for r in runs], float(np.mean([r["on_road"] for r in runs]))


def run_round(args, k):
    """Round k's data (k >= 1), policy and score, each skipped where it exists."""
    here = args.dir / f"round_{k}"
    here.mkdir(parents=True, exist_ok=True)
    policy, data = here / "policy.safetensors", here / "data.safetensors.gz"
    started = time.time()
    if k >= 1 and not data.exists():
        driver = args.dir / f"round_{k - 1}" / "policy.safetensors"
        seeds = args.tracks[(k - 1) * args.per_round:k * args.per_round]
        if len(seeds) < args.per_round:
            raise SystemExit(f"--tracks has too few tracks for round {k} ({args.per_round} a round)")
        with Pool(args.workers) as pool:
            parts = pool.map(drive_labelled, [(driver, s, args.frames, args.noise) for s in seeds], chunksize=1)
        drives = [p for p, _ in parts if p is not None]
        episodes.write(data, episodes.Episodes.concat(drives),
                       {"source": f"dagger round {k}: the round {k - 1} policy driving, the expert labelling",
                        "seeds": ",".join(map(str, seeds)), "frame_hz": "12.5", "steering_noise": str(args.noise)})
        print(f"round {k}: {sum(len(d.frames) for d in drives)} labelled frames; the round {k - 1} policy "
              f"scored {np.mean([r for _, r in parts]):.1f} on them", flush=True)
    if not policy.exists():
        files = [args.data] + [args.dir / f"round_{j}" / "data.safetensors.gz" for j in range(1, k + 1)]
        train(args, files, policy)
    scores, on_road = evaluate(args, policy, here / "heldout")
    line = {"round": k, "mean": round(float(np.mean(scores)), 1), "sd": round(float(np.std(scores)), 1),
            "min": round(float(np.min(scores)), 1), "on_road": round(on_road, 4), "tracks": len(scores),
            "seconds": round(time.time() - started, 1)}
    logged = [json.loads(t) for t in (args.dir / "log.jsonl").read_text().splitlines()] \
        if (args.dir / "log.jsonl").exists() else []
    if all(entry["round"] != k for entry in logged):
        with _files.atomic_write(args.dir / "log.jsonl") as f:
            f.write("".join(json.dumps(e) + "\n" for e in logged + [line]).encode())
    print(json.dumps(line), flush=True)
    return line


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="the expert's episodes (record --driver expert)")
    p.add_argument("--base", type=Path, default=Path("weights/default.safetensors"),
                   help="the model whose encoder and transition the policy reads (default: the repository's)")
    p.add_argument("--rounds", type=int, default=4, help="rounds after round 0 (the expert's data alone)")
    p.add_argument("--tracks", type=record.parse_seeds, required=True, help="tracks the rounds drive")
    p.add_argument("--per-round", type=int, default=16, help="tracks a round drives")
    p.add_argument("--heldout", required=True, help="tracks each round's policy is scored on")
    p.add_argument("--frames", type=int, default=1000, help="env frames a drive lasts at most")
    p.add_argument("--holdout", type=int, default=2, help="episodes train policy holds out")
    p.add_argument("--steps", type=int, default=4000, help="train policy's steps")
    p.add_argument("--workers", type=int, default=os.cpu_count(), help="processes (and trainer threads)")
    p.add_argument("--trainer", type=Path, default=Path("target/release/examples/train"),
                   help="the crate's train example (default: built in the repository, run from its root)")
    p.add_argument("--dir", type=Path, required=True, help="where rounds are written (resumable)")
    p.add_argument("--noise", type=float, default=0.0,
                   help="standard deviation of the steering offset added while a round drives (DART)")
    args = p.parse_args(argv)
    args.heldout_text, args.heldout = args.heldout, record.parse_seeds(args.heldout)
    if set(args.heldout) & set(args.tracks):
        p.error("--heldout tracks must not be driven in the rounds")
    if min(args.rounds + 1, args.per_round, args.frames, args.workers, args.steps) < 1:
        p.error("--rounds must be >= 0, and --per-round, --frames, --workers and --steps positive")
    if not (np.isfinite(args.noise) and 0.0 <= args.noise <= 1.0):
        p.error("--noise must be a number from 0 to 1")
    for path in (args.data, args.base, args.trainer):
        if not path.exists():
            p.error(f"{path}: no such file")
    args.dir.mkdir(parents=True, exist_ok=True)
    for k in range(args.rounds + 1):
        run_round(args, k)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The dream against the real track as a dream-train run goes (issue 60): for the run's saved
controllers (and generation 0, the controller it started from), the dream's return on a fixed
set of the run's real starts, under the run's own settings, beside the real CarRacing score of
the same controller on ``--tracks``.

  python -m drivesim dream-curve --dir runs/dreamt --tracks 16000-16019 [--every 50] [--workers 2]

A dream that the training exploits shows as a dream return that climbs while the real score
does not. The real drives go to ``DIR/curve/GEN/track_SEED.json`` (``python -m
drivesim.carracing``'s files: a stopped curve resumes); the table to ``DIR/curve.json``. Every
real episode is counted: these are evaluations, not a choice among checkpoints, unless the
tracks are tuning tracks.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from .._drivesim import Model, Simulator
from .._files import atomic_write
from .dreamt import Controller, default_limits, rollout
from .view import parse_seeds

#: Starts of the fixed set every controller's dream return is measured on.
CURVE_STARTS = 256


def dream_return(world: Model, run: dict, states: dict, controller: Controller, threads: int) -> tuple[float, float]:
    """The controller's mean dream return and off-road chance from ``CURVE_STARTS`` starts drawn
    once (seed 0), with the run's horizon, temperature (seed 0), off-road end and cost, value."""
    rng = np.random.default_rng(0)
    at = rng.choice(len(states["speed"]), size=CURVE_STARTS, replace=CURVE_STARTS > len(states["speed"]))
    starts = {k: np.ascontiguousarray(v[at]) for k, v in states.items()}
    sim = Simulator(world, batch=CURVE_STARTS, threads=threads)
    if run["temperature"] > 0:
        sim.set_sampling(run["temperature"], 0)
    returns, off_road = rollout(sim, controller.with_weights(controller.weights[None], controller.generation), starts,
                                run["horizon"], run["off_road_steps"], run["value"], run.get("off_road_cost", 0.0))
    return float(returns.mean()), float(off_road.mean())


def real_score(args, run: dict, path: Path, out: Path) -> list:
    """The real env's reward per track for the controller file ``path`` (resumable per track)."""
    cmd = [sys.executable, "-m", "drivesim.carracing", "--agent", "dreamt", "--set", f"controller={path}",
           "--seeds", args.tracks, "--workers", str(args.workers), "--frames", str(args.frames), "--out", str(out)]
    if run["world"] not in (None, "None"):
        cmd += ["--weights", run["world"]]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return [json.loads((out / f"track_{s}.json").read_text())["reward"] for s in parse_seeds(args.tracks)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dir", type=Path, required=True, help="a dream-train run's folder")
    p.add_argument("--tracks", required=True, help="real tracks each controller drives, e.g. 16000-16019")
    p.add_argument("--every", type=int, default=50, help="generations between the controllers measured")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--threads", type=int, default=2, help="threads of the dream's rollouts")
    args = p.parse_args(argv)
    if min(args.every, args.workers, args.frames, args.threads) < 1:
        p.error("--every, --workers, --frames and --threads must be positive")
    try:
        tracks = parse_seeds(args.tracks)
    except argparse.ArgumentTypeError as error:
        p.error(f"--tracks: {error}")
    if not (args.dir / "run.json").is_file() or not (args.dir / "states.npz").is_file():
        p.error(f"{args.dir}: not a dream-train run (no run.json and states.npz)")
    run = json.loads((args.dir / "run.json").read_text())
    world = Model.load(None if run["world"] in (None, "None") else run["world"])
    with np.load(args.dir / "states.npz") as f:
        states = {k: f[k] for k in ("z", "h", "speed")}
    limits = run.get("limits") or default_limits(world, run["base"])
    start = Controller.fit(states["z"], states["h"], run["features"], run["base"], limits)
    saved = {int(path.stem.split("_")[1]): path for path in args.dir.glob("controller_*.npz")}
    rows = []
    for generation in [0] + sorted(g for g in saved if g % args.every == 0):
        path = saved.get(generation)
        if path is None:  # generation 0: the controller the run started from
            path = args.dir / "curve" / "controller_0000.npz"
            path.parent.mkdir(parents=True, exist_ok=True)
            start.save(path)
        controller = Controller.load(path)
        dream, off = dream_return(world, run, states, controller, args.threads)
        real = real_score(args, run, path, args.dir / "curve" / f"{generation:04d}")
        rows.append({"generation": generation, "dream_return": round(dream, 2), "dream_off_road": round(off, 4),
                     "real_mean": round(float(np.mean(real)), 1), "real_sd": round(float(np.std(real)), 1),
                     "real": real})
        print(f"generation {generation:4d}: dream {dream:8.2f} (off-road {off:.3f}), real {np.mean(real):7.1f} "
              f"± {np.std(real):.1f} over {len(real)} tracks", flush=True)
    with atomic_write(args.dir / "curve.json") as f:
        f.write(json.dumps({"tracks": args.tracks, "real_episodes": len(rows) * len(tracks), "rows": rows},
                           indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

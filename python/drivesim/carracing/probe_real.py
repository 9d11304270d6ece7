"""The steering probe (drivesim.probe) in the real environment: what a perfect dream would show.

For each of the probe's starts in a recorded episodes file (`python -m drivesim record` writes the
seeds and the driver in its metadata), the recording is replayed from its seed (the scripted
driver and CarRacing are deterministic) to the start's last seed frame; then the car steers
-x, 0 or +x for 30 frames, its gas and brake holding the start's speed, and the probe reads the
road's centre after 1, 2, 3, 5, 10 and 30 frames, as `train eval` does in the dream's. Prints and writes
(--out, and the cache below) the right-way share and the symmetry for each x and number of steps:

  python -m drivesim probe-real --data held_out.safetensors.gz [--workers 2] [--out probe.json]

It is slow (the env's physics for every branch from its episode's start), so `cached` keeps
the figures beside the data, `DATA.probe-real.json`, keyed by the file's SHA-256 and the probe's
constants: `train eval --probe-real` computes them once per evaluation set.
"""

import argparse
import contextlib
import hashlib
import json
import os
import sys
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from .. import _files, episodes, probe
from . import record
from .record import car_racing


def steps(env, action, n, draw_last):
    """`n` env steps of `action`, drawing only the last where `draw_last` (drawing changes
    nothing in the physics: view.unseen); the env's reward over them."""
    reward = 0.0
    for i in range(n):
        with contextlib.nullcontext() if draw_last and i + 1 == n else record.view.unseen(env):
            reward += float(env.step(action)[1])
    return reward


def held(steer, speed, now):
    """The env's action that steers `steer` and holds the car near `speed` (units/s) from `now`:
    gas below it, the brake above it by more than 5."""
    gas = float(np.clip(0.05 * (speed - now), 0.0, 0.5))
    brake = float(np.clip(0.05 * (now - speed - 5.0), 0.0, 0.8))
    return np.array([steer, gas, brake], dtype=np.float32)


def branch(job):
    """The road centre after steering `steer` for PROBE_STEPS frames from frame `frame` of the
    recording of `seed` by `style`, and how far the replayed frame is from the recorded one
    (mean absolute difference, 0-255: the replay's check)."""
    seed, style, frame, speed, steer, recorded = job
    env = car_racing.CarRacing()
    env.reset(seed=seed)
    driver = record.Driver(env.track, np.random.default_rng(seed), style)
    steps(env, np.array([0.0, 0.3, 0.0], dtype=np.float32), record.WARMUP_STEPS, frame == 0)
    skip = 4  # the recordings' frame skip (12.5 frames per second)
    for i in range(frame):  # the recording's frames before the start
        action, _, _ = driver.act(env.car, skip / car_racing.FPS)
        steps(env, action, skip, i + 1 == frame)
    replayed = float(np.abs(record.view.observe(env).astype(np.int16) - recorded).mean())
    centres = {}
    for step in range(1, probe.PROBE_STEPS + 1):
        now = float(np.linalg.norm(env.car.hull.linearVelocity))
        steps(env, held(steer, speed, now), skip, step in probe.READINGS)
        if step in probe.READINGS:
            centres[step] = probe.centre(record.view.observe(env))
    env.close()
    return centres, replayed


def real_probe(path, workers):
    """The probe's figures in the real env for the recording `path` (see the module)."""
    data, meta = episodes.read(path), episodes.metadata(path)
    if "seeds" not in meta or "driver" not in meta:
        raise ValueError(f"{path}: no `seeds` and `driver` metadata (python -m drivesim record writes them)")
    seeds = [int(s) for s in meta["seeds"].split(",")]
    bounds = data.bounds()
    jobs = []
    for first in probe.starts(data):
        last = int(first) + probe.SEEDS - 1
        e = next(i for i, (s, end) in enumerate(bounds) if s <= last < end)
        start = (seeds[e], meta["driver"], last - bounds[e][0], float(data.actions[last, 0]))
        jobs += [(*start, steer, data.frames[last]) for x in probe.PROBE_STEER for steer in (-x, 0.0, x)]
    with Pool(workers) as pool:
        results = pool.map(branch, jobs, chunksize=1)
    out = dict(data=str(path), driver=meta["driver"], starts=len(jobs) // 6,
               replay_mean_abs_difference=float(np.mean([r for _, r in results])))
    for steps_ in probe.READINGS:
        centres = [c[steps_] for c, _ in results]
        out[str(steps_)] = {}
        for k, x in enumerate(probe.PROBE_STEER):
            per_start = [centres[i * 6 + 3 * k:i * 6 + 3 * k + 3] for i in range(len(jobs) // 6)]
            out[str(steps_)][str(x)] = probe.symmetry(*zip(*per_start))
    return out


def cached(path, workers, log=print):
    """`real_probe(path)`, from `PATH.probe-real.json` where it was computed for these bytes and
    this probe, else computed and written there."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    key = dict(sha256=digest, seeds=probe.SEEDS, starts=probe.PROBE_STARTS, steps=probe.PROBE_STEPS,
               steer=list(probe.PROBE_STEER), rows=probe.PROBE_ROWS, readings=list(probe.READINGS))
    cache = Path(f"{path}.probe-real.json")
    if cache.exists():
        kept = json.loads(cache.read_text())
        if kept.get("key") == key:
            return kept["figures"]
    log(f"probe-real: the real car's probe on {path} (once; cached in {cache})")
    figures = real_probe(path, workers)
    with _files.atomic_write(cache) as f:
        f.write(json.dumps(dict(key=key, figures=figures), indent=1).encode())
    return figures


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="episodes file recorded by python -m drivesim record")
    p.add_argument("--workers", type=int, default=os.cpu_count())
    p.add_argument("--out", help="JSON file to write the figures to")
    args = p.parse_args(argv)
    try:  # through the cache, so that `train eval --probe-real` on the same file reuses it
        out = cached(args.data, args.workers, log=lambda *_: None)
    except ValueError as e:
        p.error(str(e))
    print(json.dumps(out, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())

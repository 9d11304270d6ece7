"""Learning a driver inside the dream (issue 60): CMA-ES over a small controller on the world
model's ``[z, h]`` (``dreamt``), its only signal the world model's own reward head and off-road
chance, on drives rolled in one batch from real recorded states. No real env is touched.

  python -m drivesim dream-train --world W --starts E.safetensors.gz --dir runs/dreamt \\
      [--generations 200] [--population 32] [--starts-per-generation 32] [--horizon 40] \\
      [--temperature 1.0] [--off-road-steps 4] [--off-road-cost 0] [--value] [--base fresh|cloned]

Every generation draws its starts from the real states (the episodes ``E`` encoded by the world
model, its transition stepped along each as a driver's is), draws the population, rolls every
candidate from every start (``dreamt.rollout``; sampled futures at ``--temperature``, seeded by
the generation) and tells CMA-ES the mean returns. The guards against a dream that can be
exploited are switches: ``--temperature`` (0: the mean dream), ``--horizon`` (short drives from
real starts), ``--off-road-steps`` (a drive off the road that long earns nothing more),
``--off-road-cost`` (the off-road chance paid for at every decision), ``--value`` (the value
head at the horizon), and for a controller on the cloned policy ``--limits`` (the largest change
it may make to the clone's target speed and steering: a trust region).

``DIR`` holds ``states.npz`` (the real states, made once), ``state.npz`` (CMA-ES after the last
generation done, written atomically), ``log.jsonl`` (a line a generation: the population's mean
and best dream return, the mean's off-road chance, sigma, dream decisions per second),
``controller_GEN.npz`` every ``--save-every`` generations and ``controller.npz`` at the end (the
distribution's mean). A killed run started again with the same arguments goes on from
``state.npz`` and ends with the same bytes as one never stopped. The real score of a controller:
``python -m drivesim.carracing --agent dreamt --set controller=DIR/controller.npz --weights W``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from .. import episodes
from .._batches import batched
from .._drivesim import Model, Simulator
from .._files import atomic_write
from ..cmaes import CMAES
from .dreamt import BASES, Controller, default_limits, rollout

#: Decisions of an episode before a start may be drawn (the hidden state has seen a second).
SETTLE = 12


def real_states(world: Model, path, threads: int, batch: int = 64) -> dict:
    """Every decision of the episodes file ``path`` past its first ``SETTLE`` where the car is on
    the road (where the file records ``on_road``; a driver learns to drive from there): the code
    the world model gives its frame, the hidden state of its transition stepped along the episode
    with the recorded actions (from zeros at the episode's start), and the recorded speed."""
    data = episodes.read(path)
    sim = Simulator(world, batch=batch, threads=threads)
    codes = batched(sim.encode, data.frames, batch).reshape(-1, world.z_dim)
    step = Simulator(world, batch=1, threads=1)
    on_road = data.rewards["on_road"] if data.rewards is not None else np.ones(len(data.frames), np.uint8)
    z, h, speed = [], [], []
    for start, end in data.bounds():
        hidden = np.zeros(world.hidden_dim, np.float32)
        for t in range(start, end):
            if t - start >= SETTLE and on_road[t]:
                z.append(codes[t])
                h.append(hidden)
                speed.append(data.actions[t, 0])
            _, hidden = step.transition(codes[t], hidden, data.actions[t].astype(np.float32))
    if not z:
        raise ValueError(f"{path}: no decision on the road past an episode's first {SETTLE}")
    return {"z": np.stack(z).astype(np.float32), "h": np.stack(h).astype(np.float32),
            "speed": np.array(speed, np.float32)}


def draw_starts(states: dict, count: int, rng: np.random.Generator) -> dict:
    at = rng.choice(len(states["speed"]), size=count, replace=count > len(states["speed"]))
    return {k: np.ascontiguousarray(v[at]) for k, v in states.items()}


def settings(args) -> dict:
    """What a run's bytes depend on: a resumed run must be given the same (``--generations`` may
    grow: a run goes on to the new count)."""
    keys = ("world", "starts", "population", "starts_per_generation", "horizon", "temperature",
            "off_road_steps", "off_road_cost", "value", "base", "limits", "features", "sigma", "seed")
    return {k: str(getattr(args, k)) if isinstance(getattr(args, k), Path) else getattr(args, k) for k in keys}


def train(args, log=print) -> Controller:
    """The run ``args`` describes (see the module), from where ``args.dir`` says it stopped."""
    out = args.dir
    out.mkdir(parents=True, exist_ok=True)
    world = Model.load(args.world)
    if world.reward_width is None or (args.value and world.value_width is None):
        raise ValueError(f"{args.world or 'the default model'}: the world model needs its reward head (and the value "
                         "head for --value)")
    if args.base == "cloned" and world.policy_width is None:
        raise ValueError("--base cloned: the world model has no policy")
    if args.features > world.z_dim + world.hidden_dim:
        raise ValueError(f"--features {args.features}: [z, h] has {world.z_dim + world.hidden_dim} numbers")
    if args.temperature > 0 and not world.samples:
        raise ValueError("--temperature above 0: the world model cannot sample (no spread head); use 0")
    run = out / "run.json"
    if run.exists() and json.loads(run.read_text()) != settings(args):
        raise ValueError(f"{out}: a run with other settings is there ({run}); give another --dir")
    with atomic_write(run) as f:
        f.write(json.dumps(settings(args), indent=1).encode())
    if not (out / "states.npz").exists():
        log(f"encoding the real states of {args.starts} ...")
        with atomic_write(out / "states.npz") as f:
            np.savez(f, **real_states(world, args.starts, args.threads))
    with np.load(out / "states.npz") as f:
        states = {k: f[k] for k in ("z", "h", "speed")}
    limits = args.limits or default_limits(world, args.base)
    base = Controller.fit(states["z"], states["h"], args.features, args.base, limits)
    if (out / "state.npz").exists():
        with np.load(out / "state.npz") as f:
            es = CMAES.from_state(f)
    else:
        es = CMAES(np.zeros(base.size), args.sigma, args.population)
    lines = (out / "log.jsonl").read_text().splitlines() if (out / "log.jsonl").exists() else []
    lines = [line for line in lines if json.loads(line)["generation"] <= es.generation]  # a kill's extra line
    sim = Simulator(world, batch=(args.population + 1) * args.starts_per_generation, threads=args.threads)
    while es.generation < args.generations:
        g = es.generation
        began = time.perf_counter()
        rng = np.random.default_rng([args.seed, g])
        starts = draw_starts(states, args.starts_per_generation, rng)
        candidates = es.ask(rng)
        population = base.with_weights(np.concatenate([candidates, es.mean[None]]).reshape(-1, 2, args.features + 1), g)
        if args.temperature > 0:
            sim.set_sampling(args.temperature, args.seed * 1_000_003 + g)
        # The population and the distribution's mean, from the same starts.
        returns, off_road = rollout(sim, population, starts, args.horizon, args.off_road_steps, args.value,
                                    args.off_road_cost)
        fitness = returns.mean(axis=1)
        es.tell(candidates, -fitness[:-1])
        seconds = time.perf_counter() - began
        line = {"generation": g + 1, "mean_return": round(float(fitness[-1]), 3),
                "population_mean": round(float(fitness[:-1].mean()), 3), "best": round(float(fitness[:-1].max()), 3),
                "off_road": round(float(off_road[-1].mean()), 4), "sigma": round(es.sigma, 5),
                "decisions_per_second": round(returns.size * args.horizon / seconds)}
        lines.append(json.dumps(line))
        with atomic_write(out / "log.jsonl") as f:
            f.write(("\n".join(lines) + "\n").encode())
        with atomic_write(out / "state.npz") as f:
            np.savez(f, **es.state())
        if es.generation % args.save_every == 0:
            base.with_weights(es.mean.reshape(2, -1), es.generation).save(out / f"controller_{es.generation:04d}.npz")
        log(f"generation {line['generation']:4d}: dream return {line['mean_return']:8.2f} (population "
            f"{line['population_mean']:.2f}, best {line['best']:.2f}), off-road {line['off_road']:.3f}, sigma "
            f"{line['sigma']:.4f}, {line['decisions_per_second']} dream decisions/s")
    final = base.with_weights(es.mean.reshape(2, -1), es.generation)
    final.save(out / "controller.npz")
    return final


def pair(text: str) -> list:
    """``A,B`` as two finite numbers."""
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers A,B, got {text!r}") from None
    if not (np.isfinite(a) and np.isfinite(b)):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
    return [a, b]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", type=Path, default=None, help="the world model's weight file (default: the built-in)")
    p.add_argument("--starts", type=Path, required=True, help="episodes recorded in real CarRacing: the starts")
    p.add_argument("--dir", type=Path, required=True, help="where the run is written (resumable)")
    p.add_argument("--generations", type=int, default=200)
    p.add_argument("--population", type=int, default=32, help="controllers a generation (CMA-ES's lambda)")
    p.add_argument("--starts-per-generation", type=int, default=32, help="real states each is rolled from")
    p.add_argument("--horizon", type=int, default=40, help="decisions a dream drive lasts")
    p.add_argument("--temperature", type=float, default=1.0, help="sampled futures' temperature (0: the mean)")
    p.add_argument("--off-road-steps", type=int, default=4, help="decisions off the road that end a drive (0: never)")
    p.add_argument("--off-road-cost", type=float, default=0.0,
                   help="subtracted from a decision's reward per unit of its off-road chance")
    p.add_argument("--value", action="store_true", help="add the value head at the horizon")
    p.add_argument("--base", choices=BASES, default="fresh", help="fresh, or on top of the cloned policy")
    p.add_argument("--limits", type=pair, default=None, metavar="A,B",
                   help="fresh: the target speeds' range (default 10 to the model's top speed); cloned: the "
                        "largest change of target speed and of steering (default 10,1)")
    p.add_argument("--features", type=int, default=32, help="principal components of [z, h] the controller reads")
    p.add_argument("--sigma", type=float, default=0.1, help="CMA-ES's first step size")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save-every", type=int, default=10, help="generations between saved controllers")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    args = p.parse_args(argv)
    if min(args.generations, args.population - 3, args.starts_per_generation, args.horizon, args.features,
           args.save_every, args.threads) < 1 or args.off_road_steps < 0 or args.seed < 0:
        p.error("--generations, --starts-per-generation, --horizon, --features, --save-every and --threads must be "
                "positive, --population at least 4, --off-road-steps and --seed not negative")
    if not (np.isfinite(args.temperature) and 0 <= args.temperature <= 10 and np.isfinite(args.sigma) and args.sigma > 0
            and np.isfinite(args.off_road_cost) and args.off_road_cost >= 0):
        p.error("--temperature must be from 0 to 10, --sigma positive and --off-road-cost not negative")
    for path in (args.starts, args.world):
        if path is not None and not path.is_file():
            p.error(f"{path}: no such file")
    try:
        train(args)
    except (ValueError, episodes.EpisodesError) as error:
        print(f"python -m drivesim dream-train: error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

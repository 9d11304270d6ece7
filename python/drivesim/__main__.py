"""drivesim's commands: ``python -m drivesim COMMAND [ARGS...]`` (``COMMAND --help``: its options).

The tools that record, label, probe and judge driving live in the package beside the agents;
this is their one entry point (each is also ``python -m MODULE``)::

    python -m drivesim record --seeds 0-39 --frames 600 --out data/train.safetensors.gz
    python -m drivesim evaluate --agent mpc --seeds 1000-1019 --workers 2
"""

import importlib
import sys

#: command: (module, what it does)
COMMANDS = {
    "evaluate": ("drivesim.carracing.__main__", "score agents on real CarRacing tracks (python -m drivesim.carracing)"),
    "compare": ("drivesim.carracing.compare", "two drivers' scores compared track by track, from what the scoring commands printed"),
    "rank": ("drivesim.carracing.rank", "the rank probe: a family of drivers scored in the real env and in the dream"),
    "rank-sight": ("drivesim.carracing.rank_sight", "where the car is when off the road, real and dreamt, from a rank run's starts"),
    "reach-across": ("drivesim.carracing.reach_across", "how far across the road the dream carries the car under a recording's own actions"),
    "rank-pool": ("drivesim.carracing.rank_pool", "each driver's off-road gap pooled over several rank reports' tracks, with its error"),
    "guard": ("drivesim.carracing.guard", "how often mpc's guard lets the planner's candidates in, with a weight file"),
    "dream-train": ("drivesim.carracing.dream_train", "learn a driver inside the dream: CMA-ES on the world model's reward alone"),
    "driver": ("drivesim.driver", "a learnt driver's file apart from its world: its policy and the world's fingerprint"),
    "sampler": ("drivesim.sampler", "a texture net's file apart from its world: the sampled futures and the world's fingerprint"),
    "widen": ("drivesim.widen", "a sampler whose read-out spreads the world's mean codes wider about their mean (the judge's)"),
    "dream-curve": ("drivesim.carracing.dream_curve", "the dream's return against the real score of a dream-train run's controllers"),
    "sb3": ("drivesim.carracing.sb3", "PPO (stable-baselines3) trained in the dream unchanged, and scored on the real track"),
    "record": ("drivesim.carracing.record", "record CarRacing driving by a scripted driver as an episodes file"),
    "dagger": ("drivesim.carracing.dagger", "DAgger rounds: the cloned driver drives, the expert labels, the policy is cloned again"),
    "failures": ("drivesim.carracing.failures", "failure data: the cloned driver changed (gain, bias, speed, noise, delay), recorded"),
    "speed-model": ("drivesim.carracing.speed_model", "how the car's speed answers speed_control (the planners' speed model)"),
    "grip": ("drivesim.carracing.grip", "the grip envelope: the fastest a recorded driver goes at each amount of steering"),
    "probe-real": ("drivesim.carracing.probe_real", "the steering probe in the real CarRacing (what a perfect dream would show)"),
    "branches": ("drivesim.carracing.branches", "paired steering branches: the probe's experiment recorded as training data"),
    "join": ("drivesim.episodes", "join episodes files into one (the last file's episodes last: a trainer's --holdout)"),
    "relabel": ("drivesim.relabel", "label episodes with a teacher's policy (a policy carried to another world model)"),
    "road-cost": ("drivesim.road", "fit a RoadCost for a model on recorded episodes"),
    "convert-comma": ("drivesim.comma", "convert comma.ai research dataset drives (HDF5) to an episodes file"),
}


def usage() -> str:
    lines = ["usage: python -m drivesim COMMAND [ARGS...]    (COMMAND --help: its options)", ""]
    lines += [f"  {name:<14} {what}" for name, (_, what) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0 if argv else 2
    name = argv[0].replace("_", "-")
    if name not in COMMANDS:
        print(f"python -m drivesim: no such command: {argv[0]}\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    sys.argv[0] = f"python -m drivesim {name}"  # what argparse shows as the program
    return module.main(argv[1:]) or 0


if __name__ == "__main__":
    sys.exit(main())

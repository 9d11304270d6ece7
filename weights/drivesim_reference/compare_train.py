"""Compare one training step of drivesim (`drivesim::train`) with PyTorch eager on the CPU.

    weights/tool compare-train [--stage transition|vae-gan] [--configs default,comma] [--batch 16,256]
                               [--threads 1,2] [--seconds 1] [--rounds 3] [--no-memory]

`--stage transition` (the default): one step as `train.py` trains the transition: 15-code
windows, the first 5 inputs teacher-forced and later ones the model's own prediction
(detached), MSE, backward, gradient norm clipped to 1, Adam. `--stage vae-gan`: one
`vae_gan_step` of `train.py` on a batch of frames (batches 8,32 unless given): the
discriminator's step, then the encoder's and the generator's. The configs: `default` (80x160,
b 32, z 128, hidden 256: the trained default model's) and `comma` (b 64, z = hidden = 512).
drivesim runs in `examples/bench_report --serve` (built with `--features train`, network
`train_transition` or `train_vae_gan`), PyTorch in this process with `torch.set_num_threads`;
both on seeded random weights of the same shapes. As in
`weights/tool compare`, the runtimes take turns configuration by configuration for `--rounds`
rounds; a row's time is the median of its rounds' medians and "PyTorch/drivesim" the median
of the rounds' ratios with their range.

GFLOP counts every product of the step (`benches/common/mod.rs`): for the transition, forward
(`[W|V|U]` and `A`), the hidden state's data gradient (`[Aᵀ|Wᵀ]`) and both weight gradients;
for the VAE-GAN, every convolution and dense product of its forward and backward passes,
direct-equivalent (Winograd does fewer multiplications). "of peak" is
GFLOP/s over the FMA peak bench_report measures with as many threads at once. Peak resident
memory is measured separately, one process per runtime and configuration (1 thread), with
/usr/bin/time. "hand-off ns" is a cache line's round trip between two threads just after each
round's drivesim timing: about 50 when a 2-vCPU VM's vCPUs share a die, about 400 when the host
placed them on different dies (which slows every multi-threaded step; compare rows of one
placement).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
from pathlib import Path

import torch

from drivesim_reference.compare import ROOT, Drivesim, cpu_info, median_ms, spread
from drivesim_reference.model import Config, DriveSim, Transition

WINDOW, TEACHER = 15, 5
# name: (base channels, z, hidden)
CONFIGS = {"default": (32, 128, 256), "comma": (64, 512, 512)}
NETS = {"transition": "train_transition", "vae-gan": "train_vae_gan"}


def config(name: str) -> Config:
    base, z, hidden = CONFIGS[name]
    return Config(height=80, width=160, channels=3, base_channels=base, z_dim=z, hidden_dim=hidden, action_dim=2)


class TorchStep:
    """The reference's step of `stage` on random data, per (config, batch), made once."""

    def __init__(self, stage: str):
        self.stage = stage
        self.steps = {}

    def step(self, name: str, batch: int):
        if (name, batch) not in self.steps:
            torch.manual_seed(0)
            self.steps[(name, batch)] = (self.transition if self.stage == "transition" else self.vae_gan)(name, batch)
        return self.steps[(name, batch)]

    @staticmethod
    def transition(name: str, batch: int):
        from drivesim_reference.sequences import transition_step

        tr = Transition(config(name))
        opt = torch.optim.Adam(tr.parameters(), lr=1e-4)
        z = torch.randn(batch, WINDOW, tr.V.shape[1])
        c = torch.randn(batch, WINDOW - 1, tr.U.shape[1])
        return lambda: transition_step(tr, opt, z, c, TEACHER, 1.0)

    @staticmethod
    def vae_gan(name: str, batch: int):
        from drivesim_reference.vae_gan import ADAM_VAE_GAN, Discriminator, vae_gan_step

        cfg = config(name)
        model, dis = DriveSim(cfg).train(), Discriminator(cfg).train()
        nets = (model.encoder, model.generator, dis)
        # A small rate: the weights stay where they started, step after step (as drivesim's).
        opts = [torch.optim.Adam(m.parameters(), **dict(ADAM_VAE_GAN, lr=1e-6)) for m in nets]
        x = torch.rand(batch, cfg.channels, cfg.height, cfg.width) * 2 - 1
        eps, prior = torch.randn(batch, cfg.z_dim), torch.randn(batch, cfg.z_dim)
        return lambda: vae_gan_step(*nets, opts, x, eps, prior)

    def time(self, name, batch, threads, seconds) -> float:
        torch.set_num_threads(threads)
        return median_ms(self.step(name, batch), seconds)


def peak_rss_mib(cmd: list[str]) -> float:
    """The peak resident memory of `cmd`, from /usr/bin/time."""
    out = subprocess.run(["/usr/bin/time", "-f", "maxrss=%M", *cmd], cwd=ROOT, capture_output=True, text=True, check=True)
    line = [l for l in out.stderr.splitlines() if l.startswith("maxrss=")][-1]
    return int(line.split("=")[1]) / 1024


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stage", default="transition", choices=list(NETS))
    p.add_argument("--configs", default="default,comma")
    p.add_argument("--batch", help="batches (default 16,256 for the transition, 8,32 for the VAE-GAN)")
    p.add_argument("--threads", default="1,2")
    p.add_argument("--seconds", type=float, default=1.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--no-memory", action="store_true", help="skip the peak-memory processes")
    p.add_argument("--before", type=Path, help="another build's bench_report (--features train), timed as `before`")
    p.add_argument("--torch-only", nargs=2, metavar=("CONFIG", "BATCH"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.torch_only:  # one PyTorch configuration alone, for its peak memory
        TorchStep(a.stage).time(a.torch_only[0], int(a.torch_only[1]), 1, a.seconds)
        return 0
    net = NETS[a.stage]
    batch = a.batch or ("16,256" if a.stage == "transition" else "8,32")
    names, batches = a.configs.split(","), [int(b) for b in batch.split(",")]
    threads = [int(t) for t in a.threads.split(",")]
    if unknown := [n for n in names if n not in CONFIGS]:
        sys.exit(f"compare-train: unknown config {unknown} (default, comma)")
    subprocess.run(["cargo", "build", "--quiet", "--release", "--features", "train", "--example", "bench_report"], cwd=ROOT, check=True)
    binary = ROOT / "target" / "release" / "examples" / "bench_report"
    torch_step = TorchStep(a.stage)
    samples: dict = {}
    gflop: dict = {}
    handoff: dict = {}
    for name in names:
        base, z, hidden = CONFIGS[name]
        model_args = ["--z", str(z), "--hidden", str(hidden), "--base", str(base)]
        drivesim = Drivesim(model_args, threads, a.seconds, binary)
        builds = {"drivesim": drivesim}
        if a.before:
            builds["before"] = Drivesim(model_args, threads, a.seconds, a.before)
        try:
            for r in range(a.rounds):
                for t in threads:
                    for b in batches:
                        order = [*builds, "pytorch"]
                        for runtime in order if r % 2 == 0 else order[::-1]:
                            if runtime in builds:
                                ms = builds[runtime].time(None, net, b, t, a.seconds)
                            else:
                                ms = torch_step.time(name, b, t, a.seconds)
                            samples.setdefault((name, runtime, b, t), []).append(ms)
                print(f"{name}: round {r + 1} of {a.rounds} done", file=sys.stderr)
            gflop.update({(name, b): drivesim.gflop[(net, b)] for b in batches})
            handoff.update({(name, b, t): v for (_, b, t), v in drivesim.handoff.items()})
            peaks = drivesim.peaks
        finally:
            for build in builds.values():
                build.close()
    memory = {}
    if not a.no_memory:
        for name in names:
            base, z, hidden = CONFIGS[name]
            for b in batches:
                rust = [str(binary), "--z", str(z), "--hidden", str(hidden), "--base", str(base), "--networks", net,
                        "--batch", str(b), "--threads", "1", "--seconds", "1"]
                python = [sys.executable, "-m", "drivesim_reference.compare_train", "--stage", a.stage, "--torch-only", name, str(b),
                          "--seconds", "1"]
                memory[(name, b)] = (peak_rss_mib(rust), peak_rss_mib(python))

    model, flags = cpu_info()
    print(f"CPU: {model} ({', '.join(flags)}); torch {torch.__version__}; {a.rounds} rounds of {a.seconds} s")
    print()
    print("| config | batch | threads | drivesim ms | GFLOP/s | of peak | PyTorch ms | GFLOP/s | PyTorch/drivesim (range) "
          "| hand-off ns |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name in names:
        for t in threads:
            peak = max(v for (w, n), v in peaks.items() if n == t)
            for b in batches:
                ours, theirs = samples[(name, "drivesim", b, t)], samples[(name, "pytorch", b, t)]
                g = gflop[(name, b)]
                ratios = [p / d for p, d in zip(theirs, ours)]
                mo, mt = statistics.median(ours), statistics.median(theirs)
                print(f"| {name} | {b} | {t} | {spread(ours)} | {g / mo * 1e3:.1f} | {g / mo * 1e3 / peak:.0%} | "
                      f"{spread(theirs)} | {g / mt * 1e3:.1f} | {statistics.median(ratios):.2f}x "
                      f"({min(ratios):.2f}-{max(ratios):.2f}) | {'/'.join(f'{v:.0f}' for v in handoff.get((name, b, t), [])) or '-'} |")
    if a.before:
        print("\n`before` (another build), median ms, and per round its time over drivesim's (above 1: drivesim is faster):")
        for name in names:
            for t in threads:
                for b in batches:
                    old, ours = samples[(name, "before", b, t)], samples[(name, "drivesim", b, t)]
                    ratios = [o / d for o, d in zip(old, ours)]
                    print(f"- {name}, batch {b}, {t} thread(s): {statistics.median(old):.2f} ms; {statistics.median(ratios):.2f}x "
                          f"({min(ratios):.2f}-{max(ratios):.2f})")
    if memory:
        print()
        print("| config | batch | drivesim peak RSS MiB | PyTorch peak RSS MiB |")
        print("| --- | --- | --- | --- |")
        for (name, b), (rust, python) in memory.items():
            print(f"| {name} | {b} | {rust:.0f} | {python:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

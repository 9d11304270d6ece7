"""Compare drivesim with ONNX Runtime and PyTorch eager on the CPU.

    weights/tool compare [--z 512] [--batch 1,16] [--threads 1,2] [--seconds 1] [--rounds 3] [--out DIR]

Builds the comma config with seeded random weights, writes them as a drivesim safetensors
file and as ONNX graphs with a dynamic batch (encoder mean head, generator, transition step),
and times the three runtimes on the same weights: ONNX Runtime and PyTorch eager with their
intra-op threads pinned to each --threads value, drivesim through its `examples/bench_report`
(`--serve`, planned with the same thread counts). Prints the CPU, the FMA peak per vector
width and a markdown table of median times.

The machine may be shared and noisy, so the runtimes are interleaved: each of `--rounds`
rounds times every runtime on every network, batch and thread count for `--seconds` (one
configuration at a time, the three runtimes back to back, in alternating order). A row's
median is the median of its rounds' medians; "peer/drivesim" is the median of the rounds'
ratios of the peer's median time over drivesim's (above 1: drivesim is faster), with their
range across rounds.

drivesim alone also times a transition step fed the previous step's prediction, as in a
rollout (for f32 weights it folds `V A` into `W`), against its own and ONNX Runtime's step.

The planner's inner loop (`--planner 64x10`: candidates x steps; `--planner 0` skips it):
drivesim's `rollout_candidates` from one state and code, codes only, against the same loop
over ONNX Runtime's step, each step's predicted code and hidden state fed to the next, in
candidate steps per second.

FLOPs count every kernel tap (`benches/common/mod.rs`): about 1.04 GFLOP per frame for the
encoder and the generator at the comma config. "of peak" is GFLOP/s over the FMA peak of the
widest vector measured with as many threads at once.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

from drivesim_reference.model import Config, DriveSim, save_drivesim

ROOT = Path(__file__).resolve().parents[2]
NETWORKS = ("encode", "generate", "transition")
# Timed for drivesim alone: a transition step fed the previous step's prediction, as in a rollout,
# which drivesim recognises and runs with `V A` folded into `W` (the peers' graphs take the code).
FED_BACK = "transition_fed_back"
# A planner's inner loop (bench_report's `planner`: its steps are bench_report's PLANNER_STEPS).
PLANNER = "planner"
PLANNER_STEPS = 10
# Seconds of rest before each measurement: a runtime's worker threads spin for a while after its
# last call (ONNX Runtime's intra-op pool, PyTorch's OpenMP threads), and on two cores a spinning
# thread takes the next measurement's second core.
SETTLE = 0.3


def comma(z: int) -> Config:
    return Config(height=80, width=160, channels=3, base_channels=64, z_dim=z, hidden_dim=z, action_dim=2)


def random_model(cfg: Config, seed: int) -> DriveSim:
    torch.manual_seed(seed)
    model = DriveSim(cfg)
    with torch.no_grad():
        # Non-trivial BatchNorm statistics, so that folding them is part of the work.
        for name, buf in model.named_buffers():
            if name.endswith("running_mean"):
                buf.normal_(0.0, 0.1)
            elif name.endswith("running_var"):
                buf.uniform_(0.5, 1.5)
    return model.eval()


def inputs(cfg: Config, batch: int, seed: int = 1) -> dict[str, tuple[torch.Tensor, ...]]:
    g = torch.Generator().manual_seed(seed)
    frame = torch.rand(batch, cfg.channels, cfg.height, cfg.width, generator=g) * 2 - 1
    z = torch.randn(batch, cfg.z_dim, generator=g)
    h = torch.zeros(batch, cfg.hidden_dim)
    c = torch.randn(batch, cfg.action_dim, generator=g)
    return {"encode": (frame,), "generate": (z,), "transition": (z, h, c)}


class EncoderMean(torch.nn.Module):
    def __init__(self, model: DriveSim):
        super().__init__()
        self.encoder = model.encoder

    def forward(self, frame: torch.Tensor) -> torch.Tensor:
        return self.encoder(frame)[0]


def modules(model: DriveSim) -> dict[str, torch.nn.Module]:
    return {"encode": EncoderMean(model).eval(), "generate": model.generator, "transition": model.transition}


def export_onnx(model: DriveSim, cfg: Config, out: Path) -> dict[str, Path]:
    """The three graphs with a dynamic batch dimension."""
    names = {
        "encode": (["frame"], ["mean"]),
        "generate": (["z"], ["frame"]),
        "transition": (["z", "h", "c"], ["z_next", "h_next"]),
    }
    paths = {}
    example = inputs(cfg, 1)
    for net, module in modules(model).items():
        ins, outs = names[net]
        path = out / f"{net}.onnx"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                module, example[net], str(path), input_names=ins, output_names=outs, opset_version=17,
                dynamic_axes={n: {0: "batch"} for n in ins + outs}, dynamo=False,
            )
        paths[net] = path
    return paths


def median_ms(fn, seconds: float) -> float:
    fn()  # warm-up
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < 5 or time.perf_counter() - start < seconds:
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return times[len(times) // 2]


class Ort:
    """ONNX Runtime sessions for every network and thread count, made once."""

    def __init__(self, paths, threads):
        import onnxruntime as ort

        self.sessions = {}
        for t in threads:
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = t
            opts.inter_op_num_threads = 1
            opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            for net in NETWORKS:
                self.sessions[(net, t)] = ort.InferenceSession(str(paths[net]), opts, providers=["CPUExecutionProvider"])

    def time(self, cfg, net, batch, threads, seconds) -> float:
        if net == PLANNER:
            return self.planner(cfg, batch, threads, seconds)
        sess = self.sessions[(net, threads)]
        names = [i.name for i in sess.get_inputs()]
        feed = {n: v.numpy() for n, v in zip(names, inputs(cfg, batch)[net])}
        return median_ms(lambda: sess.run(None, feed), seconds)


    def planner(self, cfg, candidates, threads, seconds) -> float:
        """`PLANNER_STEPS` steps of `candidates` from one state and code, each step's outputs
        fed to the next, as a planner written over ONNX Runtime's step would."""
        sess = self.sessions[("transition", threads)]
        g = torch.Generator().manual_seed(4)
        z = torch.randn(1, cfg.z_dim, generator=g).repeat(candidates, 1).numpy()
        h = (torch.randn(1, cfg.hidden_dim, generator=g) * 0.5).repeat(candidates, 1).numpy()
        actions = torch.randn(PLANNER_STEPS, candidates, cfg.action_dim, generator=g).numpy()

        def run():
            code, hidden = z, h
            for c in actions:
                code, hidden = sess.run(None, {"z": code, "h": hidden, "c": c})

        return median_ms(run, seconds)


class Torch:
    """PyTorch eager, the intra-op threads set per measurement."""

    def __init__(self, model):
        self.modules = modules(model)

    def time(self, cfg, net, batch, threads, seconds) -> float:
        torch.set_num_threads(threads)
        args = inputs(cfg, batch)[net]

        def run(m=self.modules[net], a=args):
            with torch.inference_mode():
                m(*a)

        return median_ms(run, seconds)


class Drivesim:
    """The bench_report example in `--serve` mode (built by cargo, or a prebuilt `binary` on a
    machine without Rust), answering one measurement at a time."""

    def __init__(self, model_args: list[str], threads, seconds, binary: Path | None, features: str = ""):
        """`model_args`: bench_report's `--weights FILE` or `--z N [--hidden N]`; `features`:
        cargo features to build it with (`train` for the training step)."""
        cargo = ["cargo", "run", "--quiet", "--release"] + (["--features", features] if features else [])
        run = [str(binary.resolve())] if binary else cargo + ["--example", "bench_report", "--"]
        cmd = run + model_args + ["--threads", ",".join(map(str, threads)), "--seconds", str(seconds), "--serve"]
        print("$", " ".join(cmd), file=sys.stderr)
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.isa, self.peaks, self.gflop, self.handoff = "?", {}, {}, {}
        for line in self.proc.stdout:
            fields = dict(re.findall(r"(\w+)=(\S+)", line))
            if line.startswith("isa "):
                self.isa = fields["level"]
            elif line.startswith("peak "):
                self.peaks[(int(fields["width"]), int(fields.get("threads", 1)))] = float(fields["gflops"])
            elif line.strip() == "ready":
                break
        else:
            raise RuntimeError(f"bench_report exited with {self.proc.wait()} before serving")

    def time(self, cfg, net, batch, threads, seconds) -> float:
        self.proc.stdin.write(f"{net} {batch} {threads}\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line.startswith("result "):
            raise RuntimeError(f"bench_report answered {line!r} (exit status {self.proc.poll()})")
        fields = dict(re.findall(r"(\w+)=(\S+)", line))
        self.gflop[(net, batch)] = float(fields["gflop"])
        if "handoff_ns" in fields:  # with threads: the vCPUs' placement just after the timing
            self.handoff.setdefault((net, batch, threads), []).append(float(fields["handoff_ns"]))
        return float(fields["median_ms"])

    def close(self):
        self.proc.stdin.close()
        self.proc.wait()


def time_rounds(runtimes: dict, cfg, networks, batches, threads, seconds, rounds, candidates) -> dict:
    """`{(runtime, net, batch, threads): [median ms of each round]}`, the runtimes interleaved."""
    samples: dict = {}
    names = list(runtimes)
    for r in range(rounds):
        for t in threads:
            looping = [n for n in names if n != "pytorch"] if candidates else []
            for name in looping if r % 2 == 0 else looping[::-1]:
                time.sleep(SETTLE)
                ms = runtimes[name].time(cfg, PLANNER, candidates, t, seconds)
                samples.setdefault((name, PLANNER, candidates, t), []).append(ms)
            for net in networks + ((FED_BACK,) if "transition" in networks else ()):
                for b in batches:
                    # Alternate the order, so that no runtime always follows the same one.
                    for name in names if r % 2 == 0 else names[::-1]:
                        if net == FED_BACK and name in ("onnxruntime", "pytorch"):
                            continue
                        time.sleep(SETTLE)
                        ms = runtimes[name].time(cfg, net, b, t, seconds)
                        samples.setdefault((name, net, b, t), []).append(ms)
        print(f"round {r + 1} of {rounds} done", file=sys.stderr)
    return samples


def spread(values: list[float]) -> str:
    """The median of `values`, with their range when there are several."""
    m = statistics.median(values)
    return f"{m:.2f}" if len(values) == 1 else f"{m:.2f} ({min(values):.2f}-{max(values):.2f})"


def cpu_info() -> tuple[str, list[str]]:
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return platform.processor() or "unknown", []
    model = re.search(r"Model name:\s*(.+)", text)
    flags = re.search(r"Flags:\s*(.+)", text)
    have = [f for f in ("avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512_bf16") if flags and f in flags.group(1).split()]
    return (model.group(1).strip() if model else "unknown"), have


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--z", type=int, default=512, help="z_dim = hidden_dim (default 512)")
    p.add_argument("--networks", default=",".join(NETWORKS), help="of " + ", ".join(NETWORKS))
    p.add_argument("--batch", default="1,16")
    p.add_argument("--threads", default="1,2", help="peer intra-op thread counts")
    p.add_argument("--seconds", type=float, default=1.0, help="time budget per measurement and round")
    p.add_argument("--rounds", type=int, default=3, help="rounds of every measurement, interleaved")
    p.add_argument("--planner", default="64x10", help="candidates x steps of the planner loop (0: skip)")
    p.add_argument("--seed", type=int, default=2016)
    p.add_argument("--out", type=Path, help="where to write the weights and graphs (default: a temp dir)")
    p.add_argument("--bench-report", type=Path, help="a prebuilt examples/bench_report binary to run instead of cargo")
    p.add_argument("--before", type=Path, help="another build's bench_report, timed as the runtime `before` (a change's effect)")
    a = p.parse_args()
    batches = [int(b) for b in a.batch.split(",")]
    networks = tuple(a.networks.split(","))
    if not set(networks) <= set(NETWORKS):
        p.error(f"--networks: of {', '.join(NETWORKS)}")
    candidates, _, steps = a.planner.partition("x")
    candidates = int(candidates)
    if candidates and int(steps or PLANNER_STEPS) != PLANNER_STEPS:
        p.error(f"--planner: the loop has {PLANNER_STEPS} steps (bench_report's PLANNER_STEPS)")
    threads = [int(t) for t in a.threads.split(",")]
    cfg = comma(a.z)
    out = a.out or Path(tempfile.mkdtemp(prefix="drivesim-compare-"))
    out.mkdir(parents=True, exist_ok=True)

    model = random_model(cfg, a.seed)
    weights = out / "model.safetensors"
    save_drivesim(model, cfg, weights)
    paths = export_onnx(model, cfg, out)

    drivesim = Drivesim(["--weights", str(weights)], threads, a.seconds, a.bench_report)
    runtimes = {"drivesim": drivesim, "onnxruntime": Ort(paths, threads), "pytorch": Torch(model)}
    if a.before:
        runtimes["before"] = Drivesim(["--weights", str(weights)], threads, a.seconds, a.before)
    try:
        samples = time_rounds(runtimes, cfg, networks, batches, threads, a.seconds, a.rounds, candidates)
    finally:
        for rt in runtimes.values():
            if isinstance(rt, Drivesim):
                rt.close()
    gflop, peaks = drivesim.gflop, drivesim.peaks

    import onnxruntime

    name, flags = cpu_info()
    print(f"CPU: {name}; {os.cpu_count()} logical CPUs; flags: {' '.join(flags)}")
    print(f"drivesim kernels: {drivesim.isa}; onnxruntime {onnxruntime.__version__}; torch {torch.__version__}")
    print("FMA peak: " + ", ".join(f"{w}-bit {t} thread(s) {g:.1f} GFLOP/s" for (w, t), g in sorted(peaks.items())))
    print(f"config: comma 80x160, b=64, z=hidden={a.z}; f32 weights; seed {a.seed}; {a.rounds} rounds of {a.seconds} s\n")
    widest = max((w for w, _ in peaks), default=0)

    def peak(t):
        """The measured peak of `t` threads at the widest vector, else t times one thread's."""
        return peaks.get((widest, t), peaks.get((widest, 1), float("nan")) * t)

    print("| network | batch | runtime | threads | median ms | GFLOP/s | of peak | peer/drivesim (range) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for net in networks:
        for b in batches:
            for t in threads:
                own = samples[("drivesim", net, b, t)]
                for rt in runtimes:
                    times = samples[(rt, net, b, t)]
                    ms = statistics.median(times)
                    gf = gflop.get((net, b), float("nan")) / (ms / 1e3)
                    ratio = "" if rt == "drivesim" else spread([p / d for p, d in zip(times, own)])
                    print(f"| {net} | {b} | {rt} | {t} | {ms:.3f} | {gf:.1f} | {gf / peak(t):.0%} | {ratio} |")
    print(f"\ndrivesim's step fed its own prediction ({FED_BACK}), median ms, and per round its step from")
    print("a code and ONNX Runtime's step over it (above 1: the fed-back step is faster):")
    for b in batches if "transition" in networks else []:
        for t in threads:
            fed = samples[("drivesim", FED_BACK, b, t)]
            own, ort = samples[("drivesim", "transition", b, t)], samples[("onnxruntime", "transition", b, t)]
            ratios = [spread([o / f for o, f in zip(step, fed)]) for step in (own, ort)]
            line = f"- batch {b}, {t} thread(s): {statistics.median(fed):.4f} ms; own step {ratios[0]}; ONNX Runtime {ratios[1]}"
            if "before" in runtimes:
                old = samples[("before", FED_BACK, b, t)]
                line += f"; before {statistics.median(old):.4f} ms ({spread([o / f for o, f in zip(old, fed)])})"
            print(line)
    if candidates:
        print(f"\nThe planner's loop, {candidates} candidates x {PLANNER_STEPS} steps from one state and code, codes")
        print("only: drivesim's rollout_candidates, ONNX Runtime's step in a loop (above 1: drivesim is faster):")
        print("| threads | runtime | median ms | candidate steps/s | runtime/drivesim (range) |")
        print("|---:|---|---:|---:|---:|")
        for t in threads:
            own = samples[("drivesim", PLANNER, candidates, t)]
            for rt in (n for n in runtimes if n != "pytorch"):
                times = samples[(rt, PLANNER, candidates, t)]
                rate = candidates * PLANNER_STEPS / (statistics.median(times) / 1e3)
                ratio = "" if rt == "drivesim" else spread([o / d for o, d in zip(times, own)])
                print(f"| {t} | {rt} | {statistics.median(times):.3f} | {rate:,.0f} | {ratio} |")
    if 1 in batches and len(batches) > 1:
        print("\ndrivesim per item at the largest batch against batch 1, per round (above 1: batching helps):")
        big = max(batches)
        for net in networks:
            for t in threads:
                one, many = samples[("drivesim", net, 1, t)], samples[("drivesim", net, big, t)]
                print(f"- {net}, {t} thread(s): {spread([o / (m / big) for o, m in zip(one, many)])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

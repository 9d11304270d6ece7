"""Compare drivesim with ONNX Runtime and PyTorch eager on the CPU.

    weights/tool compare [--z 512] [--batch 1,16] [--threads 1,2] [--seconds 2] [--out DIR]

Builds the comma config with seeded random weights, writes them as a drivesim safetensors
file and as ONNX graphs with a dynamic batch (encoder mean head, generator, transition step),
times ONNX Runtime and PyTorch eager with their intra-op threads pinned to each --threads
value, runs drivesim's `examples/bench_report` with the same thread counts on the same weights
file, and
prints the CPU, the FMA peak per vector width and a markdown table of median times.

FLOPs count every kernel tap (`benches/common/mod.rs`): about 1.04 GFLOP per frame for the
encoder and the generator at the comma config. "of peak" is GFLOP/s over the FMA peak of the
widest vector measured with as many threads at once. "peer/drivesim" is the
peer's median time over drivesim's at the same batch and thread count (above 1: drivesim is
faster).
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

from model import Config, DriveSim, save_drivesim

ROOT = Path(__file__).resolve().parent.parent
NETWORKS = ("encode", "generate", "transition")


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
    while len(times) < 5 or (time.perf_counter() - start < seconds and len(times) < 1000):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return times[len(times) // 2]


def time_ort(paths, cfg, batches, threads, seconds):
    import onnxruntime as ort

    rows = []
    for t in threads:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = t
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        for net in NETWORKS:
            sess = ort.InferenceSession(str(paths[net]), opts, providers=["CPUExecutionProvider"])
            names = [i.name for i in sess.get_inputs()]
            for b in batches:
                feed = {n: v.numpy() for n, v in zip(names, inputs(cfg, b)[net])}
                rows.append(("onnxruntime", net, b, t, median_ms(lambda: sess.run(None, feed), seconds)))
    return rows


def time_torch(model, cfg, batches, threads, seconds):
    rows = []
    mods = modules(model)
    for t in threads:
        torch.set_num_threads(t)
        for net in NETWORKS:
            for b in batches:
                args = inputs(cfg, b)[net]

                def run(m=mods[net], a=args):
                    with torch.inference_mode():
                        m(*a)

                rows.append(("pytorch", net, b, t, median_ms(run, seconds)))
    return rows


def time_drivesim(weights: Path, batches, threads, seconds, binary: Path | None):
    """Runs the bench_report example (built by cargo, or a prebuilt `binary` on a machine
    without Rust); returns (rows, gflop per (net, batch), isa, peaks)."""
    run = [str(binary)] if binary else ["cargo", "run", "--quiet", "--release", "--example", "bench_report", "--"]
    cmd = run + [
        "--weights", str(weights), "--batch", ",".join(map(str, batches)),
        "--threads", ",".join(map(str, threads)), "--seconds", str(seconds),
    ]
    print("$", " ".join(cmd), file=sys.stderr)
    text = subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True).stdout
    rows, gflop, peaks, isa = [], {}, {}, "?"
    for line in text.splitlines():
        fields = dict(re.findall(r"(\w+)=(\S+)", line))
        if line.startswith("isa "):
            isa = fields["level"]
        elif line.startswith("peak "):
            peaks[(int(fields["width"]), int(fields.get("threads", 1)))] = float(fields["gflops"])
        elif line.startswith("result "):
            net, b = fields["network"], int(fields["batch"])
            rows.append(("drivesim", net, b, int(fields["threads"]), float(fields["median_ms"])))
            gflop[(net, b)] = float(fields["gflop"])
    return rows, gflop, isa, peaks


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
    p.add_argument("--batch", default="1,16")
    p.add_argument("--threads", default="1,2", help="peer intra-op thread counts")
    p.add_argument("--seconds", type=float, default=2.0, help="time budget per measurement")
    p.add_argument("--seed", type=int, default=2016)
    p.add_argument("--out", type=Path, help="where to write the weights and graphs (default: a temp dir)")
    p.add_argument("--bench-report", type=Path, help="a prebuilt examples/bench_report binary to run instead of cargo")
    a = p.parse_args()
    batches = [int(b) for b in a.batch.split(",")]
    threads = [int(t) for t in a.threads.split(",")]
    cfg = comma(a.z)
    out = a.out or Path(tempfile.mkdtemp(prefix="drivesim-compare-"))
    out.mkdir(parents=True, exist_ok=True)

    model = random_model(cfg, a.seed)
    weights = out / "model.safetensors"
    save_drivesim(model, cfg, weights)
    paths = export_onnx(model, cfg, out)

    ds_rows, gflop, isa, peaks = time_drivesim(weights, batches, threads, a.seconds, a.bench_report)
    rows = ds_rows + time_ort(paths, cfg, batches, threads, a.seconds) + time_torch(model, cfg, batches, threads, a.seconds)

    import onnxruntime

    name, flags = cpu_info()
    print(f"CPU: {name}; {os.cpu_count()} logical CPUs; flags: {' '.join(flags)}")
    print(f"drivesim kernels: {isa}; onnxruntime {onnxruntime.__version__}; torch {torch.__version__}")
    print("FMA peak: " + ", ".join(f"{w}-bit {t} thread(s) {g:.1f} GFLOP/s" for (w, t), g in sorted(peaks.items())))
    print(f"config: comma 80x160, b=64, z=hidden={a.z}; f32 weights; seed {a.seed}\n")
    widest = max((w for w, _ in peaks), default=0)

    def peak(t):
        """The measured peak of `t` threads at the widest vector, else t times one thread's."""
        return peaks.get((widest, t), peaks.get((widest, 1), float("nan")) * t)

    ds = {(net, b, t): ms for (_, net, b, t, ms) in ds_rows}
    print("| network | batch | runtime | threads | median ms | GFLOP/s | of peak | peer/drivesim |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for net in NETWORKS:
        for b in batches:
            for rt, n, bb, t, ms in rows:
                if n != net or bb != b:
                    continue
                gf = gflop.get((net, b), float("nan")) / (ms / 1e3)
                ratio = "" if rt == "drivesim" else f"{ms / ds[(net, b, t)]:.2f}"
                print(f"| {net} | {b} | {rt} | {t} | {ms:.3f} | {gf:.1f} | {gf / peak(t):.0%} | {ratio} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

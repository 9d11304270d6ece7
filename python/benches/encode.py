"""The Python package's cost over the Rust crate's: ``Simulator.encode`` on one 8-bit frame,
against the same call in Rust (``frames_from_rgb`` then ``encode``, bench_report's
``encode_rgb``), interleaved in rounds on one thread, medians of each.

  cargo build --release -p drivesim-examples --example bench_report
  python python/benches/encode.py --rounds 5

Prints one row per round and the ratio of the medians (Python over Rust).
"""

import argparse
import os
import subprocess
import sys
import time

import numpy as np

import drivesim

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


def python_ms(sim, frame, seconds):
    sim.encode(frame)  # warm-up
    times, start = [], time.perf_counter()
    while len(times) < 5 or time.perf_counter() - start < seconds:
        t = time.perf_counter()
        sim.encode(frame)
        times.append((time.perf_counter() - t) * 1e3)
    return float(np.median(times))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--seconds", type=float, default=2.0, help="time per measurement")
    p.add_argument("--bench-report", default=os.path.join(REPO, "target", "release", "examples", "bench_report"))
    args = p.parse_args(argv)
    if not os.path.exists(args.bench_report):
        p.error(f"{args.bench_report} is missing: cargo build --release -p drivesim-examples --example bench_report")
    weights = os.path.join(REPO, "weights", "default.safetensors")
    rust = subprocess.Popen([args.bench_report, "--weights", weights, "--seconds", str(args.seconds), "--serve"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    while rust.stdout.readline().strip() != "ready":
        pass
    sim = drivesim.Simulator(drivesim.Model.load(weights))
    frame = drivesim.load_episodes()[0][0][0]
    rows = []
    for r in range(args.rounds):
        rust.stdin.write("encode_rgb 1 1\n")
        rust.stdin.flush()
        line = rust.stdout.readline()
        rust_ms = float(line.split("median_ms=")[1].split()[0])
        py_ms = python_ms(sim, frame, args.seconds)
        rows.append((rust_ms, py_ms))
        print(f"round {r + 1}: Rust {rust_ms:.3f} ms, Python {py_ms:.3f} ms, ratio {py_ms / rust_ms:.3f}", flush=True)
    rust.stdin.close()
    rust.wait()
    rust_ms, py_ms = np.median(rows, axis=0)
    print(f"encode, one 8-bit frame, one thread: Rust {rust_ms:.3f} ms, Python {py_ms:.3f} ms "
          f"(medians of {args.rounds} rounds): Python / Rust {py_ms / rust_ms:.3f}")
    # A shared VM's speed jumps between levels for seconds at a time; the fastest round of each
    # is the figure least touched by it.
    rust_ms, py_ms = np.min(rows, axis=0)
    print(f"fastest rounds: Rust {rust_ms:.3f} ms, Python {py_ms:.3f} ms: Python / Rust {py_ms / rust_ms:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

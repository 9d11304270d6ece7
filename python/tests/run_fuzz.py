"""The long fuzz (test_fuzz.py's ``long`` profile), resumable: chunks of ``--examples`` examples
per test, each under its own hypothesis seed, until ``--calls`` API calls or ``--minutes``
have passed. Each finished chunk appends a line to ``--log`` (JSON: chunk, calls, seconds,
whether it passed), and a new run skips the chunks there, so a stopped run goes on where it
stopped. A chunk's pytest output goes beside the log (``fuzz_chunk_N.txt``).

    python python/tests/run_fuzz.py --calls 1000000 --log runs/fuzz/log.jsonl
"""

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def done_chunks(log):
    if not os.path.exists(log):
        return []
    with open(log) as f:
        return [json.loads(line) for line in f if line.strip()]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--calls", type=int, default=1_000_000, help="stop once this many calls were made in all")
    p.add_argument("--minutes", type=float, default=float("inf"), help="stop starting chunks after this long")
    p.add_argument("--examples", type=int, default=500, help="examples per test in one chunk")
    p.add_argument("--log", default="fuzz_long.jsonl", help="where finished chunks are recorded")
    args = p.parse_args(argv)
    os.makedirs(os.path.dirname(os.path.abspath(args.log)), exist_ok=True)
    chunks = done_chunks(args.log)
    start = time.monotonic()
    while True:
        calls = sum(c["calls"] for c in chunks)
        if calls >= args.calls or (time.monotonic() - start) / 60 >= args.minutes:
            break
        k = max((c["chunk"] for c in chunks), default=-1) + 1
        report = os.path.abspath(f"{args.log}.calls")
        out = os.path.join(os.path.dirname(os.path.abspath(args.log)), f"fuzz_chunk_{k}.txt")
        env = {**os.environ, "DRIVESIM_FUZZ_PROFILE": "long", "DRIVESIM_FUZZ_EXAMPLES": str(args.examples),
               "DRIVESIM_FUZZ_REPORT": report}
        t = time.monotonic()
        with open(out, "w") as f:
            rc = subprocess.call([sys.executable, "-m", "pytest", os.path.join(HERE, "test_fuzz.py"), "-q",
                                  "-p", "no:cacheprovider", f"--hypothesis-seed={k}"], stdout=f, stderr=subprocess.STDOUT,
                                 env=env, cwd=HERE)
        with open(report) as f:
            n = int(f.read())
        chunk = {"chunk": k, "calls": n, "seconds": round(time.monotonic() - t, 1), "passed": rc == 0}
        with open(args.log, "a") as f:
            f.write(json.dumps(chunk) + "\n")
        chunks.append(chunk)
        print(json.dumps(chunk), flush=True)
    calls, seconds = sum(c["calls"] for c in chunks), sum(c["seconds"] for c in chunks)
    failed = [c["chunk"] for c in chunks if not c["passed"]]
    print(f"fuzz: {calls} calls in {len(chunks)} chunks, {seconds / 60:.1f} min; failed chunks: {failed or 'none'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

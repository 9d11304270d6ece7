#!/usr/bin/env bash
# A training run killed with SIGKILL at random moments and resumed each time (--checkpoint,
# --resume) must write the same --out bytes as the run never stopped, and every file it leaves
# behind must load. Usage: examples/train/kill_resume.sh TRAIN_BINARY EPISODES [KILLS]
# (.ci/run runs it on a small episodes file; the transition command, one thread).
set -euo pipefail
train="$1" episodes="$2" kills="${3:-5}"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
args=(transition --weights weights/default.safetensors --episodes "$episodes" --steps 2000 --batch 16
      --threads 1 --checkpoint "$dir/run.ckpt" --checkpoint-every 100 --resume)
"$train" "${args[@]}" --out "$dir/whole.safetensors" > /dev/null
rm "$dir/run.ckpt"
for i in $(seq "$kills"); do
    "$train" "${args[@]}" --out "$dir/resumed.safetensors" > "$dir/log" 2>&1 &
    pid=$!
    # A random moment: loading, encoding and the first evaluation take about 2.5 s on a Zen 3
    # core, the 2,000 steps about 5 s.
    sleep 2.5
    sleep "$(printf '%d.%d' $((RANDOM % 5)) $((RANDOM % 10)))"
    kill -9 "$pid" 2> /dev/null || true
    wait "$pid" 2> /dev/null || true
    echo "kill $i: $(grep -o 'resumed at step [0-9]*' "$dir/log" || echo 'started afresh'), checkpoint at step $(
        python3 -c "import json,sys;b=open(sys.argv[1],'rb').read();n=int.from_bytes(b[8:12],'little');print(json.loads(b[12:12+n])['step'])" "$dir/run.ckpt" 2> /dev/null || echo none)"
    ls "$dir" | grep -v -x -e whole.safetensors -e run.ckpt -e log -e resumed.safetensors && {
        echo "a temporary file was left behind"; exit 1; } || true
done
"$train" "${args[@]}" --out "$dir/resumed.safetensors" | grep -o 'resumed at step [0-9]*' || true
cmp "$dir/whole.safetensors" "$dir/resumed.safetensors"
echo "kill_resume: the resumed run wrote the same bytes as the run never stopped ($kills kills)"

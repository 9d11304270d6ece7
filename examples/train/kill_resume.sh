#!/usr/bin/env bash
# A training run killed with SIGKILL at random moments and resumed each time (--checkpoint,
# --resume) must write the same --out bytes as the run never stopped, and leave no temporary
# file behind. Usage: examples/train/kill_resume.sh TRAIN_BINARY EPISODES transition|vae-gan [KILLS]
# (.ci/run runs both on a small episodes file, one thread).
set -euo pipefail
train="$1" episodes="$2" command="$3" kills="${4:-5}"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
case "$command" in
    # Loading, encoding and the first evaluation take about 2.5 s on a Zen 3 core, the 2,000
    # steps about 5 s; the VAE-GAN's start about 4 s, its 40 steps about 8 s.
    transition) extra=(--steps 2000 --batch 16 --checkpoint-every 100) start=2.5 spread=5 ;;
    vae-gan) extra=(--steps 40 --batch 2 --every 1000 --checkpoint-every 4) start=4 spread=8 ;;
    *) echo "unknown command $command"; exit 2 ;;
esac
args=("$command" --weights weights/default.safetensors --episodes "$episodes" --threads 1 "${extra[@]}"
      --checkpoint "$dir/run.ckpt" --resume)
"$train" "${args[@]}" --out "$dir/whole.safetensors" > /dev/null 2>&1
rm "$dir/run.ckpt"
step_of() {
    python3 -c "import json,sys;b=open(sys.argv[1],'rb').read();n=int.from_bytes(b[8:12],'little');print(json.loads(b[12:12+n])['step'])" "$1" 2> /dev/null || echo none
}
for i in $(seq "$kills"); do
    "$train" "${args[@]}" --out "$dir/resumed.safetensors" > "$dir/log" 2>&1 &
    pid=$!
    sleep "$start"
    sleep "$(printf '%d.%d' $((RANDOM % spread)) $((RANDOM % 10)))"
    kill -9 "$pid" 2> /dev/null || true
    wait "$pid" 2> /dev/null || true
    echo "kill $i: $(grep -o 'resumed at step [0-9]*' "$dir/log" || echo 'killed before it resumed'), checkpoint at step $(step_of "$dir/run.ckpt")"
    if ls -A "$dir" | grep -v -x -e whole.safetensors -e run.ckpt -e log -e resumed.safetensors; then
        echo "a temporary file was left behind"
        exit 1
    fi
done
"$train" "${args[@]}" --out "$dir/resumed.safetensors" 2>&1 | grep -o 'resumed at step [0-9]*' || true
cmp "$dir/whole.safetensors" "$dir/resumed.safetensors"
echo "kill_resume $command: the resumed run wrote the same bytes as the run never stopped ($kills kills)"

#!/usr/bin/env bash
# A training run killed with SIGKILL at random moments and resumed each time (--checkpoint,
# --resume) must write the same --out bytes as the run never stopped; once it has finished, no
# temporary file may be left behind. Usage: examples/train/kill_resume.sh TRAIN_BINARY EPISODES transition|vae-gan|policy|heads [KILLS]
# (.ci/run runs both on a small episodes file, one thread).
set -euo pipefail
train="$1" episodes="$2" command="$3" kills="${4:-5}"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
case "$command" in
    transition) extra=(--steps 2000 --batch 16 --checkpoint-every 100) ;;
    vae-gan) extra=(--steps 40 --batch 2 --every 1000 --checkpoint-every 4) ;;
    policy) extra=(--steps 12000 --batch 256 --checkpoint-every 500) ;;
    # The value head by TD(λ) on real and dreamed drives: its targets are recomputed at each
    # checkpoint (--refresh).
    heads) extra=(--head value --restart --dream-steps 4 --dream-every 8 --steps 6000 --batch 256 --refresh 500 --checkpoint-every 500) ;;
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
    before="$(step_of "$dir/run.ckpt")"
    "$train" "${args[@]}" --out "$dir/resumed.safetensors" > "$dir/log" 2>&1 &
    pid=$!
    # A random moment after the run (resumed) wrote a checkpoint of its own, whatever the load
    # on the machine: up to a second later, or the run's end.
    for _ in $(seq 1200); do
        [ "$(step_of "$dir/run.ckpt")" != "$before" ] && break
        kill -0 "$pid" 2> /dev/null || break
        sleep 0.1
    done
    sleep "0.$((RANDOM % 10))"
    kill -9 "$pid" 2> /dev/null || true
    wait "$pid" 2> /dev/null || true
    echo "kill $i: $(grep -o 'resumed at step [0-9]*' "$dir/log" || echo 'started afresh'), checkpoint at step $(step_of "$dir/run.ckpt")"
    # A kill mid-save may leave that save's temporary file (the file saved stays whole); nothing
    # else.
    if ls -A "$dir" | grep -v -x -e whole.safetensors -e run.ckpt -e log -e resumed.safetensors \
        -e .run.ckpt.tmp -e .resumed.safetensors.tmp; then
        echo "an unexpected file was left behind"
        exit 1
    fi
done
# What a kill in the middle of a checkpoint's save leaves, whether or not one of the kills did.
echo partial > "$dir/.run.ckpt.tmp"
"$train" "${args[@]}" --out "$dir/resumed.safetensors" 2>&1 | grep -o 'resumed at step [0-9]*' || true
cmp "$dir/whole.safetensors" "$dir/resumed.safetensors"
# The finished run removed what the killed ones left.
if ls -A "$dir" | grep -e '\.tmp$'; then
    echo "a temporary file was left behind after the run finished"
    exit 1
fi
echo "kill_resume $command: the resumed run wrote the same bytes as the run never stopped ($kills kills)"

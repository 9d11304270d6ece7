#!/bin/bash
# The training steps' (and the forward steps') scaling over 1-16 threads, this build against an
# earlier one, as docs/performance.md's "Training on many threads" table was measured on a lent
# 16-core machine. NEW and OLD are `bench_report` binaries built with
# `cargo build --release --features train --example bench_report` at the two commits; copy them
# into an ignored folder of the checkout to carry them to another machine.
#
#   benches/threads_table.sh NEW OLD [THREADS]      (THREADS: 1,2,4,8,16 by default)
set -u
new=$1 old=$2 threads=${3:-1,2,4,8,16}
weights=weights/default.safetensors
log() { echo "## $*"; }
lscpu | grep -E 'Model name|^CPU\(s\)|Thread|Core|Socket|NUMA node'
log "new transition comma b256"
"$new" --networks train_transition --batch 256 --threads "$threads" --seconds 2
log "old transition comma b256"
"$old" --networks train_transition --batch 256 --threads 1,16 --seconds 2
log "new vae_gan default b64"
"$new" --weights $weights --networks train_vae_gan --batch 64 --threads "$threads" --seconds 0
log "old vae_gan default b64"
"$old" --weights $weights --networks train_vae_gan --batch 64 --threads 1,16 --seconds 0
log "new forward comma b64"
"$new" --networks encode,generate,transition --batch 64 --threads "$threads" --seconds 1
# The old and new one-thread steps again, in turn: a pair each (the first runs warm the machine).
log "pair round 2"
"$new" --networks train_transition --batch 256 --threads 1,16 --seconds 2
"$old" --networks train_transition --batch 256 --threads 1,16 --seconds 2
"$new" --weights $weights --networks train_vae_gan --batch 64 --threads 1,16 --seconds 0
"$old" --weights $weights --networks train_vae_gan --batch 64 --threads 1,16 --seconds 0
log "comma vae_gan new"
"$new" --networks train_vae_gan --batch 64 --threads 1,16 --seconds 0
log done

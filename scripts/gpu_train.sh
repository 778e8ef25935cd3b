#!/usr/bin/env bash
# Train ctgpp on one GPU from a pack of converted scenes (scripts/pack_scenes.py), for a fixed time.
#
#   scripts/gpu_train.sh PACK.tar.xz RUN_DIR MINUTES [more `ctgpp train` options]
#
# RUN_DIR is the checkpoint directory: a run resumes where it holds a training state (carry e.g.
# training/ctgpp-v5 there), else a new run starts (its size from the options: --d-model 128 --heads 16
# is the paper's reference). The recipe is ctgpp-v5's (docs/benchmarks.md, Training: ctgpp-v5);
# the CPU recipe is the same `ctgpp train` command without --budget and --loader-workers. A 3-step run
# on the device first fails fast where it cannot train at all. Used on the lent device machine
# (issue 35): d = 128 and d = 64 were trained side by side with this recipe in its first form (commit
# d1befb1). Waymo's windows are drawn 4 times as often as the others' (ctgpp.data.sampling): its 9-s
# scenes give 1,014 of the 24,100 training windows (4 %) for 13 % of the vehicle-seconds, and they
# hold the city streets (parked cars, multi-lane roads) the intersections of INTERACTION lack.
set -euo pipefail
pack=$1 run=$2 minutes=$3
shift 3
data=/tmp/ctgpp-pack
rm -rf "$data" && mkdir -p "$data"
tar xJf "$pack" -C "$data"
export PYTHONPATH=$PWD/src PYTHONUNBUFFERED=1 OMP_NUM_THREADS=4
train=(python3 -m ctgpp.cli.main train)
"${train[@]}" --out "$data/smoke" --train mini_val --val mini_val --steps 3 --val-every 3 --val-windows 1 \
    --batch 2 --stride 40 --mirror --turn-share 0.3 --loader-workers 1 > "$data/smoke.log" 2>&1 \
    || { tail -30 "$data/smoke.log"; exit 1; }
python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU')"
limit=$(python3 -c "print(int(60 * $minutes + 240))")  # the budget, the window building, the last save
timeout "$limit" "${train[@]}" --out "$run" \
    --train "$data/interaction:train" --train "$data/waymo:train*4" --train "$data/ngsim:train" \
    --train mini_train --val mini_val --stride 10 --mirror --turn-share 0.3 --batch 64 --lr 5e-4 \
    --val-every 250 --val-windows 32 --steps 1000000 --budget "$minutes" --workers 14 --loader-workers 12 \
    "$@" > "$run.log" 2>&1 || true
tail -c 600 "$run.log"

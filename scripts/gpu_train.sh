#!/usr/bin/env bash
# Train ctgpp on one GPU from a pack of converted scenes (scripts/pack_scenes.py), two widths side by
# side: the paper's reference size (d = 128, 16 heads) and the shipped width (d = 64, 4 heads), on the
# same data, draws and time. Used on the lent device machine (issue 35); the CPU recipe is the same
# `ctgpp train` command without --budget.
#
#   scripts/gpu_train.sh PACK.tar.xz OUT MINUTES
#
# OUT receives d128/ (checkpoint and training state), d64.tar (the same for d = 64, in one file) and
# both logs. A 3-step run on the GPU first fails fast where the device cannot train at all.
set -euo pipefail
pack=$1 out=$2 minutes=$3
data=/tmp/ctgpp-pack; rm -rf "$data"; mkdir -p "$data"
tar xJf "$pack" -C "$data"
export PYTHONPATH=$PWD/src PYTHONUNBUFFERED=1 OMP_NUM_THREADS=4
train=(python3 -m ctgpp.cli.main train)
"${train[@]}" --out "$data/smoke" --train mini_val --val mini_val --steps 3 --val-every 3 --val-windows 1 \
    --batch 2 --stride 40 --mirror --turn-share 0.3 > "$out/smoke.log" 2>&1 || { tail -30 "$out/smoke.log"; exit 1; }
rm "$out/smoke.log"  # what comes back from the device is at most 8 files
python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else \"no GPU: training on the CPU\")"
common=(--train "$data/interaction:train" --train "$data/waymo:train" --train "$data/ngsim:train"
        --train mini_train --val mini_val --stride 10 --mirror --turn-share 0.3 --batch 64 --lr 5e-4
        --val-every 250 --val-windows 32 --steps 1000000 --budget "$minutes")
limit=$(python3 -c "print(int(60 * $minutes + 240))")  # the budget, the window building, the last save
timeout "$limit" "${train[@]}" --out "$out/d128" --d-model 128 --heads 16 --workers 8 "${common[@]}" \
    > "$out/d128.log" 2>&1 &
timeout "$limit" "${train[@]}" --out "$data/d64" --workers 7 "${common[@]}" > "$out/d64.log" 2>&1 &
wait || true
tar cf "$out/d64.tar" -C "$data" d64
ls -la "$out" "$out/d128"
tail -c 600 "$out/d128.log"; echo; tail -c 600 "$out/d64.log"

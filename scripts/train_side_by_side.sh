#!/bin/bash
# CTG++, its two ablations, the reference size (d = 128, 16 heads) and the CTG and BITS baselines, trained
# side by side on one GPU with the same data and recipe (docs/evaluation.md, Training records).
# Each run stops at --steps or after LIMIT seconds (its state saved at the last validation, every 250
# steps); running the script again resumes every run where it stopped. With OUT set, each run directory
# is packed into OUT (split in 15 MB parts), a finished run without its optimizer state.
#
#   LIMIT=420 bash scripts/train_side_by_side.sh            # runs/gpu-<name>
set -u
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
LIMIT=${LIMIT:-420}
STEPS=${STEPS:-8000}
common="--train mini_train --train data/ngsim:train --smooth 0.3 --stride 2 --val-every 250 --val-windows 32"
common="$common --lr 3e-4 --steps $STEPS --workers 2"
declare -A args=(
  [ctg]="--model ctg" [bits]="--model bits" [no_edge]="--variant no_edge"
  [scene_centric]="--variant scene_centric" [full]="" [full-d128]="--d-model 128 --heads 16"
)
mkdir -p runs
for name in "${!args[@]}"; do
  mkdir -p "runs/gpu-$name"
  # shellcheck disable=SC2086
  timeout -s TERM "$LIMIT" python3 -m ctgpp.cli.main train ${args[$name]} --out "runs/gpu-$name" $common \
    >> "runs/gpu-$name/train.log" 2>&1 &
done
wait
for name in "${!args[@]}"; do
  d=runs/gpu-$name
  step=$(python3 -c "import json; print(json.load(open('$d/train_state.json'))['step'])" 2>/dev/null || echo 0)
  echo "== $name: step $step"
  [ -n "${OUT:-}" ] || continue
  ex=""; [ "$step" = "$STEPS" ] && ex="--exclude=train_state.safetensors"
  tar czf "$OUT/$name.tar" $ex -C runs "gpu-$name"
  if [ "$(stat -c %s "$OUT/$name.tar")" -gt 15000000 ]; then
    split -b 15000000 -d "$OUT/$name.tar" "$OUT/$name.tar.part" && rm "$OUT/$name.tar"
  fi
done

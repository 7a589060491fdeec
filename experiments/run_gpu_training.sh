#!/usr/bin/env bash
# MB-DSC++ and MF-DSC++ side by side on one GPU for a wall-clock budget (two processes sharing the
# device), continuing runs/gpu_<env>_<algo> when a checkpoint of it exists. Writes each run's
# metrics.csv + trajectory/classifier plots and a combined curves.png under $OUT.
#
#   ENV=u_maze BUDGET=420 OUT=experiments/results/train_u_maze bash experiments/run_gpu_training.sh
set -uo pipefail
ENV=${ENV:-u_maze}
BUDGET=${BUDGET:-420}
OUT=${OUT:-experiments/results/train_${ENV}}
ALGOS=${ALGOS:-"mb_dscpp mf_dscpp"}
EXTRA=${EXTRA:-}
mkdir -p "$OUT"
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.45}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || true
pids=()
for algo in $ALGOS; do
  run=runs/gpu_${ENV}_${algo}
  if [ -d "$run/checkpoints" ] && [ -n "$(ls "$run/checkpoints" 2>/dev/null)" ]; then
    args=(--resume "$run")
  else
    args=(--env "$ENV" --algo "$algo" --seed 0 --run-dir "$run" $EXTRA)
  fi
  echo "== $algo: python -m dscpp_jax.cli train ${args[*]} --time-budget $BUDGET --no-progress --plot"
  python -m dscpp_jax.cli train "${args[@]}" --time-budget "$BUDGET" --no-progress --plot \
    2>&1 | grep -v -e "warp" -e "^WARNING" | sed "s/^/[$algo] /" &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
runs=()
for algo in $ALGOS; do
  run=runs/gpu_${ENV}_${algo}
  runs+=("$run")
  mkdir -p "$OUT/$algo"
  cp "$run/metrics.csv" "$OUT/$algo/" 2>/dev/null
  python -c "import json,sys; d=json.load(open(sys.argv[1])); print(json.dumps(d[\"versions\"]))" "$run/config.json"
  cp "$run/plots/trajectory.png" "$run/plots/classifiers.png" "$OUT/$algo/" 2>/dev/null
done
python -m dscpp_jax.cli plot "${runs[@]}" --out "$OUT" --curves-only 2>&1 | grep -v warp
ls -la "$OUT" "$OUT"/*

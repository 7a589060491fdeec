#!/usr/bin/env bash
# MB-DSC++ and MF-DSC++ on the point-mass U-maze, 3 seeds each, the CPU "fast" preset (the
# `make train` default); curves (mean +- stderr) + one run's trajectory/classifier plots under OUT.
#   bash experiments/run_cpu_point_seeds.sh
set -euo pipefail
ENV=${ENV:-point_u_maze}
OUT=${OUT:-experiments/results/train_${ENV}}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
runs=()
for algo in mb_dscpp mf_dscpp; do
  for seed in 0 1 2; do
    run=runs/cpu_${ENV}_${algo}_s${seed}
    rm -rf "$run"
    /usr/bin/time -f "$algo seed $seed: %e s wall" $PY -m dscpp_jax.cli train --env "$ENV" --algo "$algo" \
      --seed "$seed" --run-dir "$run" --no-progress 2>&1 | grep -v warp
    mkdir -p "$OUT/${algo}_s${seed}"
    cp "$run/metrics.csv" "$OUT/${algo}_s${seed}/"
    runs+=("$run")
  done
  $PY -m dscpp_jax.cli plot "runs/cpu_${ENV}_${algo}_s0" --out "$OUT/${algo}_s0" 2>&1 | grep -v warp
  rm -f "$OUT/${algo}_s0/curves.png"
done
$PY -m dscpp_jax.cli plot "${runs[@]}" --out "$OUT" --curves-only 2>&1 | grep -v warp

#!/usr/bin/env bash
# A seed group over every GPU of one host, through the command line as a user runs it: train one
# seed per GPU for a few iterations, resume the group to a longer schedule, then evaluate and
# plot one seed's directory. Writes the logs and a summary (smoke.json) under DEST.
#
#   DEST=runs/multi_gpu bash experiments/multi_gpu_smoke.sh            # ant U-maze, MB-DSC++
#   ENV=u_maze ALGO=mf_dscpp STEPS=32000 bash experiments/multi_gpu_smoke.sh
set -uo pipefail
DEST=${DEST:-runs/multi_gpu}
ENV=${ENV:-u_maze}
ALGO=${ALGO:-mb_dscpp}
STEPS=${STEPS:-32000}         # env steps per seed before the resume (the ant preset: 5 iterations)
PY=${PYTHON:-python3}
mkdir -p "$DEST"
n=$($PY -c "import jax; print(jax.local_device_count())")
seeds="0-$((n - 1))"
group="$DEST/${ENV}_${ALGO}_g$seeds"
rm -rf "$group"
step() {   # name, command...: run, time, record the exit code
  local name=$1; shift
  local t0; t0=$(date +%s.%N)
  "$@" > "$DEST/$name.log" 2>&1
  local rc=$?
  echo "\"$name\": {\"exit\": $rc, \"s\": $(python3 -c "import time; print(round(time.time() - $t0, 1))")}"
}
{
  echo "{\"devices\": $n, \"seeds\": \"$seeds\","
  step train $PY -m dscpp_jax.cli train --env "$ENV" --algo "$ALGO" --seeds "$seeds" \
    --total-steps "$STEPS" --eval-episodes 4 --run-dir "$group" --no-progress
  echo ","
  step resume $PY -m dscpp_jax.cli train --resume "$group" --total-steps $((2 * STEPS)) \
    --no-progress
  echo ","
  step eval $PY -m dscpp_jax.cli eval --run "$group/s$((n - 1))" --episodes 2 --no-plot
  echo ","
  step plot $PY -m dscpp_jax.cli plot "$group/s0" "$group/s$((n - 1))"
  echo "}"
} > "$DEST/smoke.json"
cat "$DEST/smoke.json"
for s in $(seq 0 $((n - 1))); do
  echo "s$s: $(tail -n 1 "$group/s$s/metrics.csv" | cut -c1-120)"
done

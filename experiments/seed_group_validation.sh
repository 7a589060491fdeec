#!/usr/bin/env bash
# Seed-group validation on one GPU host: 8 seeds of ant U-maze MB-DSC++ trained in one program
# (default flags, 100-episode evaluations), a recording of two evaluation episodes of seed 0 for
# the videos, then `bench_seeds.py` (N = 1..16, MF- and MB-DSC++). Lean results (group.json,
# per-seed metrics.csv / config.json / eval.json, logs, the recording, the benchmark JSON and
# table) are packed into $DEST/results.tgz after each stage, so a host taken back early keeps what
# finished.
#
#   DEST=runs/validation bash experiments/seed_group_validation.sh
#   SEEDS=0-7 ENV=u_maze ALGO=mb_dscpp BENCH_SEEDS=1,2,4,8,16 ...   (the defaults; EXTRA: more
#   train flags)
set -uo pipefail
DEST=${DEST:-runs/validation}
SEEDS=${SEEDS:-0-7}
ENV=${ENV:-u_maze}
ALGO=${ALGO:-mb_dscpp}
BENCH_SEEDS=${BENCH_SEEDS:-1,2,4,8,16}
BENCH_ALGOS=${BENCH_ALGOS-"mf_dscpp mb_dscpp"}
BENCH_TIMEOUT=${BENCH_TIMEOUT:-420}
export DSCPP_JAX_COMPILE_CACHE=${DSCPP_JAX_COMPILE_CACHE:-$PWD/runs/xla_cache}
GROUP=$DEST/${ENV}_${ALGO}_g${SEEDS}
mkdir -p "$DEST"
log() { echo "[$(date +%T)] $*" | tee -a "$DEST/stages.log"; }

pack() {
  (cd "$DEST" && find . \( -name metrics.csv -o -name config.json -o -name eval.json \
      -o -name group.json -o -name '*.log' -o -name episodes.npz -o -name 'bench_*.json' \
      -o -name 'bench_*.md' \) -print0 | tar czf results.tgz.tmp --null -T - \
      && mv results.tgz.tmp results.tgz)
}

{ nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || echo "no GPU"; } > "$DEST/gpu.log" 2>&1
log "train $ENV $ALGO seeds $SEEDS"
python3 -m dscpp_jax.cli train --env "$ENV" --algo "$ALGO" --seeds "$SEEDS" --eval-episodes 100 \
  --run-dir "$GROUP" --no-progress ${EXTRA:-} > "$DEST/train.log" 2>&1
log "train exit $?"
pack
log "record seed 0"
python3 -m dscpp_jax.cli video --run "$GROUP/s0" --record-only --episodes 2 > "$DEST/record.log" 2>&1
log "record exit $?"
pack
for a in $BENCH_ALGOS; do
  log "bench $a"
  timeout "$BENCH_TIMEOUT" python3 experiments/bench_seeds.py --env "$ENV" --algos "$a" \
    --seeds-list "$BENCH_SEEDS" --out "$DEST/bench_seeds_$a.json" > "$DEST/bench_$a.log" 2>&1
  log "bench $a exit $?"
  pack
done
log done

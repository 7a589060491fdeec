#!/usr/bin/env bash
# Time to result on one GPU host with the default flags (`make train ENV=...`): the ant preset
# evaluates in-band (32 envs, success every iteration) and 100 episodes at the end.
#
#   DEST=runs/ttr bash experiments/time_to_result.sh
#   STAGES="probe cold warm" SEEDS_COLD="0" SEEDS_WARM="1 2 3 4" FOUR_ROOMS_ALGO=mf_dscpp
#
# Stages:
#   probe       where the start of a run goes (experiments/compile_breakdown.py), on empty caches
#   cold        U-maze MB-DSC++, seeds SEEDS_COLD one after another, each on empty caches (XLA's
#               and MuJoCo Warp's kernel cache)
#   warm        U-maze MB-DSC++, seeds SEEDS_WARM one after another, on the warm caches
#   four_rooms  four rooms, FOUR_ROOMS_ALGO seed 0, warm caches of its own config (a first
#               compile of its own: its cache entries are not U-maze's)
# Each run's whole command is timed into time_NAME.json; lean results are packed into
# $DEST/results.tgz after each stage, so a host taken back early keeps what finished.
set -uo pipefail
DEST=${DEST:-runs/ttr}
STAGES=${STAGES:-"probe cold warm"}
SEEDS_COLD=${SEEDS_COLD:-0}
SEEDS_WARM=${SEEDS_WARM:-"1 2 3 4"}
FOUR_ROOMS_ALGO=${FOUR_ROOMS_ALGO:-mf_dscpp}
export DSCPP_JAX_COMPILE_CACHE=${DSCPP_JAX_COMPILE_CACHE:-$PWD/$DEST/xla_cache}
mkdir -p "$DEST"
log() { echo "[$(date +%T)] $*" | tee -a "$DEST/stages.log"; }
pack() {
  (cd "$DEST" && find . -path ./xla_cache -prune -o \( -name metrics.csv -o -name config.json \
      -o -name eval.json -o -name '*.log' -o -name 'time_*.json' -o -name 'compile_*.json' \) \
      -print0 | tar czf results.tgz.tmp --null -T - && mv results.tgz.tmp results.tgz)
}
# MuJoCo Warp's kernel cache: WARP_CACHE_PATH where set (a cache of its own for this script, so
# that emptying it leaves other runs on the host alone), else ~/.cache/warp.
empty_caches() { rm -rf "$DSCPP_JAX_COMPILE_CACHE" "${WARP_CACHE_PATH:-$HOME/.cache/warp}"; }
{ nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || echo "no GPU"; } \
  > "$DEST/gpu.log" 2>&1
train_timed() {   # name, then train arguments: wall-clock of the whole command into time_NAME.json
  local name=$1; shift
  local t0; t0=$(date +%s.%N)
  python3 -m dscpp_jax.cli train "$@" --run-dir "$DEST/$name" --no-progress > "$DEST/$name.log" 2>&1
  local rc=$?
  local dt; dt=$(python3 -c "import time; print(round(time.time() - $t0, 1))")
  echo "{\"name\": \"$name\", \"exit\": $rc, \"command_s\": $dt}" > "$DEST/time_$name.json"
  log "$name exit $rc ($dt s)"
}
for stage in $STAGES; do
  case $stage in
    probe)
      empty_caches
      log "probe: compile breakdown, u_maze mb_dscpp, empty caches"
      python3 experiments/compile_breakdown.py --env u_maze --algo mb_dscpp \
        --out "$DEST/compile_cold.json" > "$DEST/probe_cold.log" 2>&1
      log "probe cold exit $?"
      python3 experiments/compile_breakdown.py --env u_maze --algo mb_dscpp \
        --out "$DEST/compile_warm.json" > "$DEST/probe_warm.log" 2>&1
      log "probe warm exit $?" ;;
    cold)
      for s in $SEEDS_COLD; do
        empty_caches
        log "cold: u_maze mb_dscpp seed $s"
        train_timed "u_maze_s${s}_cold" --env u_maze --algo mb_dscpp --seed "$s"
        pack
      done ;;
    warm)
      for s in $SEEDS_WARM; do
        log "warm: u_maze mb_dscpp seed $s"
        train_timed "u_maze_s${s}_warm" --env u_maze --algo mb_dscpp --seed "$s"
        pack
      done ;;
    four_rooms)
      log "four rooms: $FOUR_ROOMS_ALGO seed 0"
      train_timed "four_rooms_${FOUR_ROOMS_ALGO}_s0" --env four_rooms --algo "$FOUR_ROOMS_ALGO" \
        --seed 0 ;;
  esac
  pack
done
log done

#!/usr/bin/env bash
# Time to result on one GPU host, from a cold start: ant U-maze MB-DSC++ (seed 0) with in-band
# evaluation, first on empty compilation caches (XLA's and MuJoCo Warp's kernel cache), then the
# same command again on the warm caches; then an ant four-rooms MF-DSC++ seed group. Recordings of
# evaluation episodes for the videos are saved beside the runs. Lean results are packed into
# $DEST/results.tgz after each stage, so a host taken back early keeps what finished.
#
#   DEST=runs/ttr bash experiments/time_to_result.sh
#   INBAND=32 GROUP_ENV=four_rooms GROUP_ALGO=mf_dscpp GROUP_SEEDS=0-3 STAGES="cold warm group"
set -uo pipefail
DEST=${DEST:-runs/ttr}
INBAND=${INBAND:-32}
GROUP_ENV=${GROUP_ENV:-four_rooms}
GROUP_ALGO=${GROUP_ALGO:-mf_dscpp}
GROUP_SEEDS=${GROUP_SEEDS:-0-3}
STAGES=${STAGES:-"cold warm group"}
export DSCPP_JAX_COMPILE_CACHE=${DSCPP_JAX_COMPILE_CACHE:-$PWD/$DEST/xla_cache}
mkdir -p "$DEST"
log() { echo "[$(date +%T)] $*" | tee -a "$DEST/stages.log"; }
pack() {
  (cd "$DEST" && find . -path ./xla_cache -prune -o \( -name metrics.csv -o -name config.json \
      -o -name eval.json -o -name group.json -o -name '*.log' -o -name episodes.npz \
      -o -name 'time_*.json' \) -print0 | tar czf results.tgz.tmp --null -T - \
      && mv results.tgz.tmp results.tgz)
}
{ nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || echo "no GPU"; } \
  > "$DEST/gpu.log" 2>&1
train_timed() {   # name, then train arguments: wall-clock of the whole command into time_NAME.json
  local name=$1; shift
  local t0; t0=$(date +%s.%N)
  python3 -m dscpp_jax.cli train "$@" --no-progress > "$DEST/$name.log" 2>&1
  local rc=$?
  local dt; dt=$(python3 -c "import time; print(round(time.time() - $t0, 1))")
  echo "{\"name\": \"$name\", \"exit\": $rc, \"command_s\": $dt}" > "$DEST/time_$name.json"
  log "$name exit $rc ($dt s)"
}
for stage in $STAGES; do
  case $stage in
    cold|warm)
      [ "$stage" = cold ] && rm -rf "$DSCPP_JAX_COMPILE_CACHE" "$HOME/.cache/warp"
      log "$stage: u_maze mb_dscpp seed 0, in-band $INBAND"
      train_timed "u_maze_$stage" --env u_maze --algo mb_dscpp --seed 0 --eval-every 0 \
        --eval-episodes 100 --set "inband_eval_envs=$INBAND" --run-dir "$DEST/u_maze_$stage"
      if [ "$stage" = cold ]; then
        python3 -m dscpp_jax.cli video --run "$DEST/u_maze_cold" --record-only --episodes 2 \
          > "$DEST/record_u_maze.log" 2>&1
        log "record u_maze exit $?"
      fi ;;
    group)
      log "group: $GROUP_ENV $GROUP_ALGO seeds $GROUP_SEEDS, in-band 16"
      train_timed "${GROUP_ENV}_group" --env "$GROUP_ENV" --algo "$GROUP_ALGO" \
        --seeds "$GROUP_SEEDS" --eval-every 0 --eval-episodes 100 --set inband_eval_envs=16 \
        --run-dir "$DEST/${GROUP_ENV}_${GROUP_ALGO}_g$GROUP_SEEDS"
      python3 -m dscpp_jax.cli video --run "$DEST/${GROUP_ENV}_${GROUP_ALGO}_g$GROUP_SEEDS/s${GROUP_SEEDS%%[-,]*}" \
        --record-only --episodes 2 > "$DEST/record_$GROUP_ENV.log" 2>&1
      log "record $GROUP_ENV exit $?" ;;
  esac
  pack
done
log done

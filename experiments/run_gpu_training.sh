#!/usr/bin/env bash
# Several trainings at once on the GPUs of one host, each for a wall-clock budget, continuing
# runs/gpu_<env>_<algo> when a checkpoint of it exists. Each job: train (ant `fast` preset),
# evaluate the final state on EVAL_EPISODES episodes from the task start, write its plots. Results
# (metrics.csv, config.json, eval.json, plots, logs) go to $OUT/<env>_<algo>/, combined curves to
# $OUT/curves_<env>.png, and everything into $OUT/results.tgz.
#
#   JOBS="0:u_maze:mb_dscpp 1:four_rooms:mb_dscpp 2:u_maze:mf_dscpp" BUDGET=420 OUT=out \
#     bash experiments/run_gpu_training.sh
#   ENV=u_maze ALGOS="mb_dscpp mf_dscpp" BUDGET=420 bash experiments/run_gpu_training.sh  # one GPU
#
# A job is GPU:ENV:ALGO[:TAG]; jobs naming the same GPU share it (memory split evenly), or, with
# SERIAL=1, run on it one after another (each with the whole GPU).
# EXTRA is appended to every fresh run's command line (e.g. EXTRA="--set max_options=20"), and
# ARGS_<TAG> to the fresh runs of jobs tagged TAG (e.g. ARGS_b1k="--set td3_batch_size=1024");
# a tagged job's run and results are named <env>_<algo>_<tag>; BUDGET_<TAG> overrides BUDGET for it.
# Stopped by a signal (e.g. `timeout`), it still packs results.tgz from what the jobs have written.
# DETERMINISTIC=1 passes --deterministic, 0 --no-deterministic; unset, train and eval choose
# (deterministic XLA kernels except on MuJoCo Warp physics, which does not repeat either way).
# Compiled programs are kept in $DSCPP_JAX_COMPILE_CACHE (default runs/xla_cache).
set -uo pipefail
ENV=${ENV:-u_maze}
BUDGET=${BUDGET:-420}
OUT=${OUT:-experiments/results/train_${ENV}}
ALGOS=${ALGOS:-"mb_dscpp mf_dscpp"}
EXTRA=${EXTRA:-}
EVAL_EPISODES=${EVAL_EPISODES:-100}  # 100: a standard error of about 0.03 at 0.9 (32 gave about 0.05)
SERIAL=${SERIAL:-0}
DET_ARG=
# compiled programs next to the runs, so a resumed chunk or an evaluation loads them
export DSCPP_JAX_COMPILE_CACHE=${DSCPP_JAX_COMPILE_CACHE:-$PWD/runs/xla_cache}
[ "${DETERMINISTIC:-}" = 1 ] && DET_ARG=--deterministic
[ "${DETERMINISTIC:-}" = 0 ] && DET_ARG=--no-deterministic
if [ -z "${JOBS:-}" ]; then
  JOBS=""
  for a in $ALGOS; do JOBS="$JOBS 0:$ENV:$a"; done
fi
mkdir -p "$OUT"
nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader 2>/dev/null || true

declare -A per_gpu
for j in $JOBS; do g=${j%%:*}; per_gpu[$g]=$(( ${per_gpu[$g]:-0} + 1 )); done

name_of() {  # env algo [tag]
  if [ -n "${3:-}" ]; then echo "${1}_${2}_${3}"; else echo "${1}_${2}"; fi
}

run_job() {  # gpu env algo [tag]
  local gpu=$1 env=$2 algo=$3 tag=${4:-}
  local name; name=$(name_of "$env" "$algo" "$tag")
  local run=runs/gpu_$name dest=$OUT/$name
  local tag_args=""
  if [ -n "$tag" ]; then local v="ARGS_$tag"; tag_args=${!v:-}; fi
  local budget=$BUDGET
  if [ -n "$tag" ]; then local b="BUDGET_$tag"; budget=${!b:-$BUDGET}; fi
  local share=${per_gpu[$gpu]}
  [ "$SERIAL" = 1 ] && share=1
  local frac
  frac=$(python3 -c "print(round(0.9 / $share, 2))")
  export CUDA_VISIBLE_DEVICES=$gpu XLA_PYTHON_CLIENT_MEM_FRACTION=$frac
  local args
  if [ -d "$run/checkpoints" ] && [ -n "$(ls "$run/checkpoints" 2>/dev/null)" ]; then
    args=(--resume "$run")
  else
    args=(--env "$env" --algo "$algo" --seed 0 --run-dir "$run" $EXTRA $tag_args)
  fi
  mkdir -p "$dest"
  echo "== [gpu $gpu] python -m dscpp_jax.cli train ${args[*]} --time-budget $budget --no-progress --plot $DET_ARG"
  python -m dscpp_jax.cli train "${args[@]}" --time-budget "$budget" --no-progress --plot $DET_ARG \
    > "$dest/train.log" 2>&1
  if [ "$EVAL_EPISODES" -gt 0 ]; then  # 0: no separate evaluation (e.g. a chunk to be resumed)
    python -m dscpp_jax.cli eval --run "$run" --episodes "$EVAL_EPISODES" $DET_ARG > "$dest/eval.log" 2>&1
  fi
  collect "$run" "$dest"
  grep -v -e "warp" -e "^WARNING" "$dest/train.log" | tail -n 4 | sed "s/^/[$name] /"
}

collect() {  # run_dir dest: copy a run's results next to its logs
  cp "$1/metrics.csv" "$1/config.json" "$1/eval.json" "$2/" 2>/dev/null
  cp "$1/plots/trajectory.png" "$1/plots/classifiers.png" "$1/eval_trajectory.png" "$2/" 2>/dev/null
}

pack() {  # everything under $OUT into $OUT/results.tgz
  local tmp_tgz
  tmp_tgz=$(mktemp --suffix .tgz) && tar czf "$tmp_tgz" -C "$OUT" --exclude results.tgz . \
    && mv "$tmp_tgz" "$OUT/results.tgz"
}

# Stopped early (e.g. by `timeout`): stop the jobs, keep what they have written so far (a run
# continues from its last checkpoint when the same job runs again).
pids=()
on_stop() {
  trap '' TERM INT  # handle a stop once, even if another signal arrives while packing
  echo "stopped: packing the results written so far"
  for p in "${pids[@]}"; do pkill -TERM -P "$p"; kill "$p"; done 2>/dev/null
  for j in $JOBS; do
    IFS=: read -r _ e a t <<< "$j"
    n=$(name_of "$e" "$a" "$t")
    collect "runs/gpu_$n" "$OUT/$n"
  done
  pack
  exit 124
}
trap on_stop TERM INT

if [ "$SERIAL" = 1 ]; then
  for g in "${!per_gpu[@]}"; do
    (
      for j in $JOBS; do
        IFS=: read -r gpu env algo tag <<< "$j"
        [ "$gpu" = "$g" ] && run_job "$gpu" "$env" "$algo" "$tag"
      done
    ) &
    pids+=($!)
  done
else
  for j in $JOBS; do
    IFS=: read -r gpu env algo tag <<< "$j"
    run_job "$gpu" "$env" "$algo" "$tag" &
    pids+=($!)
  done
fi
for p in "${pids[@]}"; do wait "$p"; done

for env in $(for j in $JOBS; do IFS=: read -r _ e _ <<< "$j"; echo "$e"; done | sort -u); do
  runs=()
  for j in $JOBS; do
    IFS=: read -r _ e a t <<< "$j"
    [ "$e" = "$env" ] && runs+=("runs/gpu_$(name_of "$e" "$a" "$t")")
  done
  python -m dscpp_jax.cli plot "${runs[@]}" --out "$OUT/plots_$env" --curves-only 2>&1 | grep -v warp
  cp "$OUT/plots_$env/curves.png" "$OUT/curves_$env.png" 2>/dev/null && rm -rf "$OUT/plots_$env"
done
for j in $JOBS; do
  IFS=: read -r _ e a t <<< "$j"
  n=$(name_of "$e" "$a" "$t")
  python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], {k: round(v, 3) if isinstance(v, float) else v for k, v in d.items() if '/' not in k or k in ('eval/success_rate', 'eval/steps_to_goal', 'eval/num_options', 'eval/flipped_rate', 'eval/flipped_failures', 'eval/option_failures_per_episode', 'eval/global_option_share')})" \
    "runs/gpu_$n/eval.json" "$n" 2>/dev/null
done
pack
ls -la "$OUT"

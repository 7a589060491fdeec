#!/usr/bin/env bash
# Does one seed give the same run twice on a GPU, with and without XLA's deterministic-ops switch,
# and what does the switch cost? Four GPUs: GPUs 0 and 1 train with
# XLA_FLAGS=--xla_gpu_deterministic_ops=true, GPUs 2 and 3 without; each GPU trains ALGOS one after
# another (same seed, ITERS train_steps, ant `fast` preset), then the metrics.csv of the two runs
# of each setting are compared column by column (timings excepted).
#
#   OUT=out ENV=u_maze ALGOS="mb_dscpp mf_dscpp" ITERS=24 bash experiments/check_gpu_determinism.sh
#
# On one H200 per run, 24 iterations of both algorithms take about 9 minutes with the switch on.
# Runs cut short still leave their metrics.csv in runs/det_*; SUMMARY_ONLY=1 skips the training and
# compares the CSVs already in $OUT (over the iterations both runs of a pair have).
set -uo pipefail
ENV=${ENV:-u_maze}
ALGOS=${ALGOS:-"mb_dscpp mf_dscpp"}
ITERS=${ITERS:-20}
OUT=${OUT:-experiments/results/gpu_determinism}
mkdir -p "$OUT"
steps=$((ITERS * 128 * 50))
[ "${SUMMARY_ONLY:-0}" = 1 ] || for g in 0 1 2 3; do
  (
    export CUDA_VISIBLE_DEVICES=$g
    if [ "$g" -lt 2 ]; then export XLA_FLAGS="--xla_gpu_deterministic_ops=true"; tag=det; else tag=default; fi
    for a in $ALGOS; do
      run=runs/det_${ENV}_${a}_${tag}_g$g
      rm -rf "$run"
      # the switch is set here, for both settings alike, rather than by the CLI's --deterministic
      python -m dscpp_jax.cli train --env "$ENV" --algo "$a" --seed 0 --run-dir "$run" \
        --total-steps "$steps" --eval-every 10 --checkpoint-every 0 --no-progress \
        --no-deterministic > "$OUT/${ENV}_${a}_${tag}_g$g.log" 2>&1
      cp "$run/metrics.csv" "$OUT/${ENV}_${a}_${tag}_g$g.csv"
    done
  ) &
done
wait
python3 - "$OUT" "$ENV" $ALGOS <<'PY'
import csv, json, sys
out, env, algos = sys.argv[1], sys.argv[2], sys.argv[3:]
def load(a, tag, g):
    return list(csv.DictReader(open(f"{out}/{env}_{a}_{tag}_g{g}.csv")))
summary = {}
for a in algos:
    for tag, gs in (("det", (0, 1)), ("default", (2, 3))):
        r0, r1 = load(a, tag, gs[0]), load(a, tag, gs[1])
        n = min(len(r0), len(r1))
        r0, r1 = r0[:n], r1[:n]
        keys = [k for k in r0[0] if k != "wall_clock" and not k.startswith("time/")]
        first = next((int(x["iteration"]) for x, y in zip(r0, r1)
                      if any(x[k] != y[k] for k in keys)), None)
        it_s = [float(x["time/iteration_s"]) for r in (r0, r1) for x in r[n // 2:]]
        summary[f"{a}/{tag}"] = dict(
            iterations_compared=n, identical=first is None,
            first_differing_iteration=first,
            median_iteration_s=sorted(it_s)[len(it_s) // 2],
            env_steps=r0[-1]["env_steps"], episodes=r0[-1]["episodes"])
    d, n = summary[f"{a}/det"], summary[f"{a}/default"]
    summary[f"{a}/det_cost"] = round(d["median_iteration_s"] / n["median_iteration_s"], 3)
json.dump(summary, open(f"{out}/summary.json", "w"), indent=1)
print(json.dumps(summary, indent=1))
PY

"""Time to result: run one `train` command and stop it when its in-band success first reaches a
threshold over a full window, or at a time limit.

    python experiments/time_to_threshold.py --dest runs/ttt --name four_rooms_s0 --threshold 0.8 \
        --limit 420 -- --env four_rooms --algo mf_dscpp --seed 0

The clock starts with the command (imports, env build and compile included). The run must
evaluate in-band (`inband_eval_envs > 0`, as the ant presets do); a window counts once it holds
as many finished episodes as the run's in-band window. Writes DEST/NAME/ (the run directory),
DEST/NAME.log (its output) and DEST/time_NAME.json: the threshold, the first iteration at or above
it (iteration, episodes, the loop's wall-clock, seconds from the command's start), or null when
the run ended or hit the limit first. The run is stopped where the threshold is seen, so it has no
final evaluation: this measures time to a result, not the result at the end of training.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def first_hit(metrics_path: str, threshold: float, window: int):
    """The first metrics row whose full in-band window is at or above `threshold`, else None."""
    try:
        with open(metrics_path) as f:
            rows = list(csv.DictReader(f))
    except OSError:
        return None
    for r in rows:
        try:
            if float(r["inband/window"]) >= window and float(r["inband/success_rate"]) >= threshold:
                return dict(iteration=int(float(r["iteration"])), episodes=int(float(r["episodes"])),
                            loop_s=float(r["wall_clock"]), success=float(r["inband/success_rate"]))
        except (KeyError, ValueError):
            continue
    return None


def inband_window(run_dir: str):
    """The run's in-band window from its config.json (None until it is written)."""
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            c = json.load(f)["config"]
    except (OSError, KeyError, ValueError):
        return None
    return c["inband_eval_window"] if c.get("inband_eval_window", 0) > 0 else c["inband_eval_envs"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dest", required=True)
    p.add_argument("--name", required=True)
    p.add_argument("--threshold", type=float, default=0.9)
    p.add_argument("--limit", type=float, default=600.0, help="stop after this many seconds")
    p.add_argument("train_args", nargs=argparse.REMAINDER, help="-- then the train arguments")
    a = p.parse_args(argv)
    train_args = a.train_args[1:] if a.train_args[:1] == ["--"] else a.train_args
    if not train_args:
        p.error("give the train arguments after --")
    if any(x == "--run-dir" or x.startswith("--run-dir=") for x in train_args):
        p.error("--run-dir is DEST/NAME; leave it out of the train arguments")
    os.makedirs(a.dest, exist_ok=True)
    run_dir = os.path.join(a.dest, a.name)
    cmd = [sys.executable, "-m", "dscpp_jax.cli", "train", *train_args, "--run-dir", run_dir,
           "--no-progress"]
    t0 = time.time()
    with open(os.path.join(a.dest, f"{a.name}.log"), "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        hit, window = None, None
        while proc.poll() is None and time.time() - t0 < a.limit:
            time.sleep(1.0)
            window = window or inband_window(run_dir)
            if window == 0:
                proc.kill()
                proc.wait()
                sys.exit("the run does not evaluate in-band (inband_eval_envs=0): nothing to time")
            if window:
                hit = first_hit(os.path.join(run_dir, "metrics.csv"), a.threshold, window)
                if hit:
                    hit["command_s"] = round(time.time() - t0, 1)
                    break
        ended = proc.poll()
        if ended is None:
            proc.kill()
        proc.wait()
    if hit is None and window:   # the run may have ended with a last row at or above it
        hit = first_hit(os.path.join(run_dir, "metrics.csv"), a.threshold, window)
    out = dict(name=a.name, command=" ".join(["python", "-m", "dscpp_jax.cli", "train"] + train_args),
               threshold=a.threshold, window=window, hit=hit, stopped_s=round(time.time() - t0, 1),
               stopped_by="threshold" if hit else ("limit" if ended is None else f"exit {ended}"))
    with open(os.path.join(a.dest, f"time_{a.name}.json"), "w") as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()

"""Time to result: run one `train` command and stop it when its in-band success first reaches a
threshold over a full window, or at a time limit.

    python experiments/time_to_threshold.py --dest runs/ttt --name four_rooms_s0 --threshold 0.8 \
        --limit 420 -- --env four_rooms --algo mf_dscpp --seed 0

    # several seeds one after another (NAME_s0, NAME_s1, ...), on the caches the first one leaves,
    # with a summary table; --goal counts the runs at the threshold within that many seconds
    python experiments/time_to_threshold.py --dest runs/ttt --name u_maze --seeds 0-4 --goal 120 \
        -- --env u_maze --algo mb_dscpp

The clock starts with the command (imports, env build and compile included). The run must
evaluate in-band (`inband_eval_envs > 0`, as the ant presets do); a window counts once it holds
as many finished episodes as the run's in-band window. Writes DEST/NAME/ (the run directory),
DEST/NAME.log (its output) and DEST/time_NAME.json: the threshold, the first iteration at or above
it (iteration, episodes, the loop's wall-clock, seconds from the command's start), or null when
the run ended or hit the limit first (then `end`: the iteration and episodes it got to, and its
final evaluation's success where the run finished). The run is stopped where the threshold is seen, so it has no
final evaluation: this measures time to a result, not the result at the end of training.
Every call also writes DEST/summary_NAME.{json,md}: per run the first iteration's end (loop
seconds), the median seconds per iteration in and after the warm-up, and the hit; rewritten after
each run, so an interrupted series keeps the runs it finished. The hit's `command_s` is when this
script saw the row (it reads metrics.csv once a second); `row_s` is when the run wrote it, by the
run's own clock (its start-up record's loop start plus the row's wall-clock).
`experiments/plot_time_to_threshold.py` draws one or more summaries.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
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
    _dscpp_jax()
    from dscpp_jax.config import flat_config   # pure Python: no JAX
    c = flat_config(c)
    return c["inband_eval_window"] if c.get("inband_eval_window", 0) > 0 else c["inband_eval_envs"]


def _dscpp_jax():
    """Make the checkout's dscpp_jax importable (the script may run from any directory)."""
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)


def iteration_times(metrics_path: str):
    """From a run's metrics.csv: when its first iteration ended (loop seconds) and the median
    seconds per iteration during the warm-up and after it (None where there are none)."""
    _dscpp_jax()
    from dscpp_jax.run_logging import read_metrics
    try:
        m = read_metrics(metrics_path)
    except OSError:
        return dict(first_s=None, warmup_s=None, after_s=None)
    wall = m.get("wall_clock", [])
    flags = m.get("train/warmup", [0.0] * len(wall))
    warm, after = [], []
    for prev, t, flag in zip(wall, wall[1:], flags[1:]):
        (warm if flag > 0 else after).append(t - prev)
    med = lambda xs: round(statistics.median(xs), 3) if xs else None
    return dict(first_s=round(wall[0], 1) if wall else None, warmup_s=med(warm), after_s=med(after))


def startup_of(run_dir: str):
    """The run's first start-up record (its startup.jsonl, written by `train` after the first
    iteration), or None where there is none."""
    _dscpp_jax()
    from dscpp_jax.run_logging import read_startup
    records = read_startup(run_dir)
    return records[0] if records else None


def loop_start_s(startup):
    """Seconds from the process's start to the start of its training loop (where metrics.csv's
    `wall_clock` counts from), from its start-up record; None where that is not known."""
    try:
        return float(startup["command_to_first_iteration_s"]) - float(
            startup["phases_s"]["first iteration"])
    except (KeyError, TypeError, ValueError):
        return None


def row_s(out):
    """When the hit's metrics row was written, in seconds from the process's start by the run's own
    clock (its loop start plus the row's `wall_clock`). The timer polls metrics.csv once a second,
    so `command_s` can be up to about a second later. None where either is not known."""
    start, hit = loop_start_s(out.get("startup")), out.get("hit")
    return None if start is None or not hit else round(start + hit["loop_s"], 1)


def run_end(run_dir: str):
    """Where a run that stopped short of the threshold got to: its last metrics row's iteration and
    episodes, and its final evaluation's success from the start (eval.json) where it wrote one.
    None where it wrote no metrics row."""
    _dscpp_jax()
    from dscpp_jax.run_logging import read_metrics
    try:
        m = read_metrics(os.path.join(run_dir, "metrics.csv"))
        out = dict(iteration=int(m["iteration"][-1]), episodes=int(m["episodes"][-1]),
                   final_success=None)
    except (OSError, IndexError, KeyError, ValueError):
        return None
    try:
        with open(os.path.join(run_dir, "eval.json")) as f:
            out["final_success"] = float(json.load(f)["eval/success_rate"])
    except (OSError, KeyError, TypeError, ValueError):
        pass
    return out


def not_reached(r) -> str:
    """The summary's words for a run without a hit: what stopped it, and where it had got to."""
    by, at, end = r.get("stopped_by"), r.get("stopped_s"), r.get("end")
    where = ""
    if end:
        where = f" at iteration {end['iteration']}, {end['episodes']:,} episodes"
        if end.get("final_success") is not None:
            where += f", final success {end['final_success']:.2f}"
    if by == "limit":
        return f"not reached within the limit ({at} s){where}"
    if by == "exit 0":
        return f"not reached: the run ended{where} ({at} s)"
    return f"not reached (stopped by {by} at {at} s){where}"


def summary_table(rows, goal=None) -> str:
    """A Markdown table of time_to_threshold results (one dict per run: name, hit, times)."""
    def f(x, fmt):
        return "-" if x is None else format(x, fmt)
    out = ["| run | command to the first iteration's end | first iteration ends (loop) | "
           "s / iteration (warm-up / after) | threshold: iteration, episodes | "
           "command start to threshold | the row, by the run's clock |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        h, t = r.get("hit"), r.get("times") or {}
        st = (r.get("startup") or {}).get("command_to_first_iteration_s")
        out.append(f"| {r['name']} | {f(st, '.1f')} s | {f(t.get('first_s'), '.1f')} s | "
                   f"{f(t.get('warmup_s'), '.2f')} / "
                   f"{f(t.get('after_s'), '.2f')} | "
                   + (f"{h['iteration']}, {h['episodes']:,} | {h['command_s']:.0f} s | "
                      f"{f(h.get('row_s'), '.1f')} s |" if h else
                      f"{not_reached(r)} | - | - |"))
    secs = sorted(r["hit"]["command_s"] for r in rows if r.get("hit"))
    line = f"\n\n{len(secs)} of {len(rows)} runs reached the threshold"
    if secs:
        line += f"; command start to threshold {secs[0]:.0f}-{secs[-1]:.0f} s, median {statistics.median(secs):.0f} s"
    if goal is not None:
        line += f"; within {goal:g} s: {sum(s <= goal for s in secs)} of {len(rows)}"
    return "\n".join(out) + line + "\n"


def time_one(dest: str, name: str, train_args, threshold: float, limit: float) -> dict:
    """Run one train command until its in-band window first reaches `threshold` (or `limit`
    seconds pass, or it ends); write DEST/NAME/, DEST/NAME.log and DEST/time_NAME.json."""
    run_dir = os.path.join(dest, name)
    cmd = [sys.executable, "-m", "dscpp_jax.cli", "train", *train_args, "--run-dir", run_dir,
           "--no-progress"]
    t0 = time.time()
    with open(os.path.join(dest, f"{name}.log"), "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        hit, window = None, None
        while proc.poll() is None and time.time() - t0 < limit:
            time.sleep(1.0)
            window = window or inband_window(run_dir)
            if window == 0:
                proc.kill()
                proc.wait()
                sys.exit("the run does not evaluate in-band (inband_eval_envs=0): nothing to time")
            if window:
                hit = first_hit(os.path.join(run_dir, "metrics.csv"), threshold, window)
                if hit:
                    hit["command_s"] = round(time.time() - t0, 1)
                    break
        ended = proc.poll()
        if ended is None:
            proc.kill()
        proc.wait()
    if hit is None and window:   # the run may have ended with a last row at or above it
        hit = first_hit(os.path.join(run_dir, "metrics.csv"), threshold, window)
    out = dict(name=name, command=" ".join(["python", "-m", "dscpp_jax.cli", "train"] + train_args),
               threshold=threshold, window=window, hit=hit, stopped_s=round(time.time() - t0, 1),
               stopped_by="threshold" if hit else ("limit" if ended is None else f"exit {ended}"),
               end=None if hit else run_end(run_dir))
    with open(os.path.join(dest, f"time_{name}.json"), "w") as f:
        json.dump(out, f, indent=1)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dest", required=True)
    p.add_argument("--name", required=True)
    p.add_argument("--threshold", type=float, default=0.9)
    p.add_argument("--limit", type=float, default=600.0, help="stop after this many seconds")
    p.add_argument("--seeds", default=None,
                   help="run once per seed (0-4, 0-3,7), one after another, as NAME_sSEED")
    p.add_argument("--goal", type=float, default=None,
                   help="seconds: the summary counts the runs at the threshold within it")
    p.add_argument("train_args", nargs=argparse.REMAINDER, help="-- then the train arguments")
    a = p.parse_args(argv)
    train_args = a.train_args[1:] if a.train_args[:1] == ["--"] else a.train_args
    if not train_args:
        p.error("give the train arguments after --")
    if any(x == "--run-dir" or x.startswith("--run-dir=") for x in train_args):
        p.error("--run-dir is DEST/NAME; leave it out of the train arguments")
    seeds = None
    if a.seeds is not None:
        _dscpp_jax()
        from dscpp_jax.seed_group import parse_seeds
        try:
            seeds = parse_seeds(a.seeds)
        except ValueError as e:
            p.error(str(e))
        if any(x in ("--seed", "--seeds") or x.startswith(("--seed=", "--seeds="))
               for x in train_args):
            p.error("--seeds gives each run its --seed; leave --seed/--seeds out of the train "
                    "arguments")
    os.makedirs(a.dest, exist_ok=True)
    runs = [(a.name, train_args)] if seeds is None else \
        [(f"{a.name}_s{s}", [*train_args, "--seed", str(s)]) for s in seeds]
    results = []
    for name, targs in runs:
        out = time_one(a.dest, name, targs, a.threshold, a.limit)
        out["times"] = iteration_times(os.path.join(a.dest, name, "metrics.csv"))
        out["startup"] = startup_of(os.path.join(a.dest, name))
        if out.get("hit"):
            out["hit"]["row_s"] = row_s(out)
        print(json.dumps(out), flush=True)
        results.append(out)
        with open(os.path.join(a.dest, f"summary_{a.name}.json"), "w") as f:
            json.dump(dict(threshold=a.threshold, goal_s=a.goal, runs=results), f, indent=1)
        with open(os.path.join(a.dest, f"summary_{a.name}.md"), "w") as f:
            f.write(summary_table(results, a.goal))
    print(summary_table(results, a.goal))
    return results


if __name__ == "__main__":
    main()

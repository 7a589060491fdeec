"""Draw time-to-threshold series (the summaries `experiments/time_to_threshold.py` writes).

    python experiments/plot_time_to_threshold.py DEST1/summary_u_maze.json DEST2/summary_u_maze.json \
        --goal 120 --goal 180 --out time_to_threshold.png

Left: each run's in-band success from the start against seconds since its command started (its
loop's `wall_clock` plus the loop's start from the run's start-up record), the threshold and the
goals as lines. Right: each run's seconds to the threshold, sorted. A run whose XLA compile of
`init` and `train_step` took longer than `--compiled-s` seconds (default 30) is drawn as one that
compiled its programs (an empty XLA cache), the others as warm. The run directories are looked up
next to each summary (DEST/NAME/metrics.csv), as time_to_threshold.py leaves them.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COMPILE_PHASE = "XLA compile ahead (init, train_step)"


def load_runs(summaries, compiled_s: float = 30.0):
    """One dict per run of the given summary files: name, compiled (bool), threshold, hit seconds
    (the run's own clock where known, else when the timer saw it; None if not reached), when the
    timer stopped it, and the curve (seconds since the command's start, in-band success; full
    windows only). A run not reached is drawn as a hatched outline up to its stop."""
    for path in (ROOT, os.path.join(ROOT, "experiments")):
        if path not in sys.path:
            sys.path.insert(0, path)
    from dscpp_jax.run_logging import read_metrics
    import time_to_threshold as ttt
    runs = []
    for path in summaries:
        try:
            with open(path) as f:
                summary = json.load(f)
        except (OSError, ValueError) as e:
            raise SystemExit(f"cannot read the summary {path}: {e}")
        dest = os.path.dirname(os.path.abspath(path))
        for r in summary.get("runs", []):
            startup = r.get("startup") or {}
            start = ttt.loop_start_s(startup)
            compile_s = (startup.get("phases_s") or {}).get(COMPILE_PHASE)
            hit = r.get("hit")
            hit_s = None
            if hit:
                hit_s = hit.get("row_s") or ttt.row_s(r) or hit.get("command_s")
            xs, ys = [], []
            metrics = os.path.join(dest, r["name"], "metrics.csv")
            if start is not None and os.path.exists(metrics):
                m = read_metrics(metrics)
                window = r.get("window") or 0
                for t, w, s in zip(m.get("wall_clock", []), m.get("inband/window", []),
                                   m.get("inband/success_rate", [])):
                    if w >= window > 0:
                        xs.append(start + t)
                        ys.append(s)
            runs.append(dict(name=r["name"], threshold=r.get("threshold", summary.get("threshold")),
                             compiled=compile_s is not None and compile_s > compiled_s,
                             hit_s=hit_s, stopped_s=r.get("stopped_s"), curve=(xs, ys)))
    return runs


def short_names(names):
    """The names without the prefix they all share, cut at an underscore (u_maze_s3 and
    u_maze_cold_s3 give s3 and cold_s3)."""
    prefix = os.path.commonprefix(list(names))
    cut = prefix.rfind("_") + 1 if len(names) > 1 else 0
    return [n[cut:] or n for n in names]


def plot(runs, goals, out: str, title: str = ""):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    if not runs:
        raise SystemExit("no runs in the summaries given")
    colors = {True: "tab:red", False: "tab:blue"}
    labels = {True: "XLA programs compiled (empty cache)", False: "warm caches"}
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw=dict(width_ratios=[3, 2]))
    seen = set()
    for r in runs:
        xs, ys = r["curve"]
        lab = None if r["compiled"] in seen else labels[r["compiled"]]
        seen.add(r["compiled"])
        a.plot(xs, ys, color=colors[r["compiled"]], lw=1, alpha=0.7, label=lab)
        if r["hit_s"] is not None:
            a.plot([r["hit_s"]], [r["threshold"]], "o", color=colors[r["compiled"]], ms=3)
    thresholds = sorted({r["threshold"] for r in runs if r["threshold"] is not None})
    for th in thresholds:
        a.axhline(th, color="0.4", ls=":", lw=1)
    for g in goals:
        a.axvline(g, color="k", ls="--", lw=1)
        b.axhline(g, color="k", ls="--", lw=1)
    a.set_xlabel("seconds since the command's start")
    a.set_ylabel("in-band success from the start (full windows)")
    a.set_ylim(-0.02, 1.02)
    a.legend(loc="upper left", fontsize=8)
    order = sorted(runs, key=lambda r: (r["hit_s"] is None, r["hit_s"] or 0.0))
    for i, r in enumerate(order):
        if r["hit_s"] is not None:
            b.bar(i, r["hit_s"], color=colors[r["compiled"]])
        else:   # not reached: a hatched outline up to where the run stopped
            b.bar(i, r["stopped_s"] or 0.0, color="none", edgecolor=colors[r["compiled"]],
                  hatch="//")
    b.set_xticks(range(len(order)))
    b.set_xticklabels(short_names([r["name"] for r in order]), rotation=90, fontsize=7)
    b.set_ylabel("seconds to the threshold (run's clock);\nhatched: not reached, stopped there")
    missed = [r["name"] for r in runs if r["hit_s"] is None]
    b.set_title(f"{len(runs) - len(missed)} of {len(runs)} reached it"
                + (f"; not: {', '.join(missed)}" if missed else ""), fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("summaries", nargs="+", help="summary_NAME.json files of time_to_threshold.py")
    p.add_argument("--out", required=True, help="the PNG to write")
    p.add_argument("--goal", type=float, action="append", default=[],
                   help="seconds: draw a goal line (repeat for several)")
    p.add_argument("--compiled-s", type=float, default=30.0,
                   help="a run whose XLA compile ahead took longer compiled its programs")
    p.add_argument("--title", default="")
    a = p.parse_args(argv)
    runs = load_runs(a.summaries, a.compiled_s)
    out = plot(runs, a.goal, a.out, a.title)
    print(out)
    return runs


if __name__ == "__main__":
    main()

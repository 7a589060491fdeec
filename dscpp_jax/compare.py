"""Settings compared side by side: a table of what a few groups of runs reached, and when.

A study compares settings (a preset against a changed field), each trained as one or more seed
groups. What it asks of each setting is the same few numbers: the final success from the start
(mean and standard error over seeds), how many iterations the in-band success from the start
took to first reach a threshold, how fast the chain grew (the iteration at which K options were
mature), from which episode the chain covered the start for good, how many failed evaluation
episodes ended with the ant on its back (and how much of training it spent there), and what an
iteration cost. This module reads them off
the lean files of each run (``metrics.csv``, ``eval.json``, ``config.json``; no checkpoint), so
it works on results copied off a GPU host.

``python -m dscpp_jax.cli compare "LABEL=RUN_OR_GROUP_DIR" ...`` prints one Markdown column per
label (entries with one label are pooled, e.g. two 8-seed samples of one setting); ``--json``
writes the same numbers, per run and per label.

Every "first reached" figure is the first logged iteration at which the metric is at or above
the level; a run that never got there counts in "n of N" and not in the median. The in-band
window lags the policy (``docs/run_directory.md``, "metrics"), the same for every setting.
"""
from __future__ import annotations

import json
import math
import os
import statistics
from typing import Optional, Sequence

from dscpp_jax.diagnose import mean_se
from dscpp_jax.plots import split_label
from dscpp_jax.run_dir import is_group_dir, seed_dirs
from dscpp_jax.run_logging import read_metrics

SOLVED = 0.8   # as in ``diagnose``: final success at or above this counts the run as solved


def _finite(values) -> list:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def first_at(metrics: dict, column: str, level: float) -> Optional[tuple]:
    """(iteration, episodes) of the first row whose ``column`` is at or above ``level``; None
    when no row is (or the column is missing)."""
    vals = metrics.get(column)
    if not vals:
        return None
    for i, v in enumerate(vals):
        if math.isfinite(v) and v >= level:
            return int(metrics["iteration"][i]), float(metrics["episodes"][i])
    return None


def covered_for_good_from(metrics: dict) -> Optional[float]:
    """Training episodes at the first iteration from which the chain covered the start in every
    logged iteration to the end (``options/start_covered``); None when the start is not covered
    at the end or the run has no skill chain."""
    cov = metrics.get("options/start_covered")
    if not cov or not cov[-1] > 0.5:
        return None
    i = len(cov) - 1
    while i > 0 and cov[i - 1] > 0.5:
        i -= 1
    return float(metrics["episodes"][i])


def seconds_per_iteration(metrics: dict) -> Optional[float]:
    """Median seconds per iteration after the warm-up (``time/iteration_s`` where
    ``train/warmup`` is 0; differences of ``wall_clock`` where the run did not log those)."""
    warm = metrics.get("train/warmup")
    per = metrics.get("time/iteration_s")
    if per is None:
        wall, it = metrics.get("wall_clock"), metrics.get("iteration")
        if not wall or len(wall) < 2:
            return None
        per = [math.nan] + [(wall[i] - wall[i - 1]) / max(it[i] - it[i - 1], 1.0)
                            for i in range(1, len(wall))]
    vals = _after_warmup(per, warm)
    return statistics.median(vals) if vals else None


def _after_warmup(values, warm) -> list:
    """The finite ``values`` of the rows logged after the warm-up (``warm``: the
    ``train/warmup`` column, or None where the run did not log it)."""
    return [v for i, v in enumerate(values)
            if math.isfinite(v) and not (warm and math.isfinite(warm[i]) and warm[i] > 0)]


def on_back_share(metrics: dict) -> Optional[float]:
    """Mean ``train/on_back_share`` after the warm-up: the share of training env steps that ended
    with the ant on its back. None where the run did not log it (point masses log 0)."""
    share, warm = metrics.get("train/on_back_share"), metrics.get("train/warmup")
    if not share:
        return None
    vals = _after_warmup(share, warm)
    return statistics.mean(vals) if vals else None


def read_run(run_dir: str, levels: Sequence[float], mature: Sequence[int]) -> dict:
    """What one run reached (see the module docstring). Raises ValueError when ``run_dir`` holds
    no ``metrics.csv`` or that has no rows."""
    path = os.path.join(run_dir, "metrics.csv")
    if not os.path.isfile(path):
        raise ValueError(f"{run_dir}: no metrics.csv; compare reads each run's metrics.csv and "
                         f"eval.json (a run directory, or a seed group's directory for all its "
                         f"seeds)")
    m = read_metrics(path)
    if not m.get("iteration"):
        raise ValueError(f"{path} has no rows: the run has not finished an iteration")
    ev, episodes = {}, math.nan
    if os.path.isfile(os.path.join(run_dir, "eval.json")):
        with open(os.path.join(run_dir, "eval.json")) as f:
            ev = json.load(f)
    if os.path.isfile(os.path.join(run_dir, "config.json")):
        with open(os.path.join(run_dir, "config.json")) as f:
            episodes = float(json.load(f).get("config", {}).get("eval_episodes", math.nan))
    success = float(ev.get("eval/success_rate", math.nan))
    chain = "options/num_mature" in m
    opts = m.get("options/num_options")
    return {
        "run": run_dir,
        "success": success,
        "failures": (round((1.0 - success) * episodes)
                     if math.isfinite(success) and math.isfinite(episodes) else None),
        "falls": (float(ev["eval/flipped_failures"]) if "eval/flipped_failures" in ev
                  else None),
        "inband_first": {f"{lv:g}": first_at(m, "inband/success_rate", lv) for lv in levels},
        "mature_first": ({str(k): first_at(m, "options/num_mature", k) for k in mature}
                         if chain else None),
        "covered_from": covered_for_good_from(m),
        "chain": chain,
        "options_end": int(opts[-1]) if opts and math.isfinite(opts[-1]) else None,
        "episodes_end": float(m["episodes"][-1]),
        "s_per_iteration": seconds_per_iteration(m),
        "on_back_share": on_back_share(m),
    }


def expand(entries: Sequence[str]) -> dict:
    """{label: [run_dir, ...]} from "LABEL=DIR" or plain "DIR" entries (a plain entry's label is
    its directory's name); a seed group's directory stands for its seeds. Raises ValueError
    naming every entry that is not a directory."""
    missing = [e for e in entries if not os.path.isdir(split_label(e)[1])]
    if missing:
        raise ValueError(f"not a run or group directory: {', '.join(missing)}")
    out: dict = {}
    for e in entries:
        label, d = split_label(e)
        label = label if label is not None else os.path.basename(os.path.normpath(d))
        runs = seed_dirs(d) if is_group_dir(d) else [d]
        out.setdefault(label, []).extend(runs)
    return out


def summarize(runs: Sequence[dict], levels: Sequence[float], mature: Sequence[int]) -> dict:
    """The label's column: the runs' numbers pooled (medians, means and standard errors over
    runs)."""
    n = len(runs)
    succ = _finite(r["success"] for r in runs)
    ms = mean_se(succ)
    out = {"runs": n, "finished": len(succ),
           "success_mean": ms[0] if ms else None, "success_se": ms[1] if ms else None,
           "success_per_run": [r["success"] for r in runs],
           "solved": sum(s >= SOLVED for s in succ)}
    out["inband_first"] = {}
    for lv in levels:
        its = [r["inband_first"][f"{lv:g}"][0] for r in runs if r["inband_first"][f"{lv:g}"]]
        out["inband_first"][f"{lv:g}"] = {
            "reached": len(its), "iterations": its,
            "median": statistics.median(its) if its else None,
            "mean": statistics.mean(its) if its else None}
    chains = [r for r in runs if r["chain"]]
    out["chain_runs"] = len(chains)
    out["mature_first"] = {}
    for k in mature:
        its = [r["mature_first"][str(k)][0] for r in chains if r["mature_first"][str(k)]]
        out["mature_first"][str(k)] = {"reached": len(its),
                                       "median": statistics.median(its) if its else None}
    cov = [r["covered_from"] for r in chains if r["covered_from"] is not None]
    out["covered"] = {"runs": len(cov), "median_episodes": statistics.median(cov) if cov else None}
    opts = [r["options_end"] for r in chains if r["options_end"] is not None]
    out["options_end"] = [min(opts), max(opts)] if opts else None
    fell = [r for r in runs if r["falls"] is not None and r["failures"] is not None]
    out["falls"] = ([int(sum(r["falls"] for r in fell)), int(sum(r["failures"] for r in fell))]
                    if fell else None)
    back = _finite(r["on_back_share"] for r in runs)
    out["on_back_share"] = [statistics.mean(back), min(back), max(back)] if back else None
    spi = _finite(r["s_per_iteration"] for r in runs)
    out["s_per_iteration"] = statistics.median(spi) if spi else None
    return out


def compare(entries: Sequence[str], levels: Sequence[float] = (0.1, 0.5, 0.9),
            mature: Sequence[int] = (1, 3, 5, 9)) -> dict:
    """{label: {"runs": [read_run ...], "summary": summarize(...)}} for ``entries`` (see
    :func:`expand`). Raises ValueError on levels outside (0, 1] or option counts below 1."""
    bad = [lv for lv in levels if not 0 < lv <= 1]
    if bad:
        raise ValueError(f"--levels {bad}: success levels lie in (0, 1]")
    if any(k < 1 for k in mature):
        raise ValueError(f"--mature {list(mature)}: counts of mature options are >= 1")
    out = {}
    for label, dirs in expand(entries).items():
        runs = [read_run(d, levels, mature) for d in dirs]
        out[label] = {"runs": runs, "summary": summarize(runs, levels, mature)}
    return out


def _g(v, fmt: str = "g") -> str:
    return "-" if v is None else format(v, fmt)


def format_table(result: dict) -> str:
    """A Markdown table, one column per label, one row per number."""
    labels = list(result)
    cols = [result[lb]["summary"] for lb in labels]
    if not cols:
        return ""
    levels = list(cols[0]["inband_first"])
    mature = list(cols[0]["mature_first"])
    rows = [("runs (with a final evaluation)", [f"{c['runs']} ({c['finished']})" for c in cols]),
            ("final success from the start, mean ± s.e.",
             ["-" if c["success_mean"] is None else
              f"{c['success_mean']:.2f} ± {c['success_se']:.2f}" for c in cols]),
            ("per run", [" ".join("-" if not math.isfinite(s) else f"{s:.2f}"
                                  for s in c["success_per_run"]) for c in cols]),
            (f"runs at >= {SOLVED:g}", [f"{c['solved']} of {c['finished']}" for c in cols])]
    for lv in levels:
        rows.append((f"in-band >= {lv} first: runs, median (mean) iteration",
                     [f"{x['reached']} of {c['runs']}" + (
                         "" if x["median"] is None else
                         f", {_g(x['median'])} ({x['mean']:.1f})")
                      for c in cols for x in [c["inband_first"][lv]]]))
    for k in mature:
        rows.append((f"{k} mature option{'s' if k != '1' else ''}: median iteration",
                     ["-" if not c["chain_runs"] else
                      f"{_g(x['median'])}" + ("" if x["reached"] == c["chain_runs"] else
                                             f" ({x['reached']} of {c['chain_runs']})")
                      for c in cols for x in [c["mature_first"][k]]]))
    rows += [("start covered for good: runs, from (median episodes)",
              ["-" if not c["chain_runs"] else
               f"{c['covered']['runs']} of {c['chain_runs']}"
               + ("" if c["covered"]["median_episodes"] is None
                  else f", {c['covered']['median_episodes']:,.0f}") for c in cols]),
             ("options at the end", ["-" if not c["options_end"] else
                                     f"{c['options_end'][0]}-{c['options_end'][1]}" for c in cols]),
             ("failed final-evaluation episodes on the back",
              ["-" if not c["falls"] else f"{c['falls'][0]} of {c['falls'][1]}" for c in cols]),
             ("training steps on the back after the warm-up: mean share (runs' range)",
              ["-" if not c["on_back_share"] else
               "{:.1%} ({:.1%}-{:.1%})".format(*c["on_back_share"]) for c in cols]),
             ("seconds per iteration after the warm-up, median",
              [_g(c["s_per_iteration"], ".2f") for c in cols])]
    lines = ["| | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
    lines += [f"| {name} | " + " | ".join(cells) + " |" for name, cells in rows]
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def write_json(result: dict, path: str) -> None:
    """The numbers behind :func:`format_table`, per run and per label (NaN as null)."""
    d = os.path.dirname(path)
    if d:
        os.makedirs(d, exist_ok=True)
    with open(path, "w") as f:
        json.dump(_jsonable(result), f, indent=1)

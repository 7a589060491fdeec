"""Why a run's skill chain fails from the start: a reading of its ``metrics.csv`` and ``eval.json``.

The skill chain can fail from the task start in a few recurring ways, each visible in what a run
already writes (``docs/cli.md``, "diagnose"; the medium maze in ``experiments/results/README.md``):

- ``falls``: the chain reaches the start, and most failed evaluation episodes end with the ant on
  its back (``eval/flipped_failures``);
- ``weak link``: the chain reaches the start, but one of its options fails most of its
  evaluation executions (``eval/option_success/K`` below ``WEAK_LINK``), often because its
  parent's region lies on both sides of a junction;
- ``table full``: no option's region holds the start and every row of the option table is in use
  (``options/capacity_hit``), so no link can be added;
- ``stalled link``: no option's region holds the start and the link in gestation has failed at
  least ``STALLED_LINK_EXECUTIONS`` executions without a success;
- ``not covered``: no option's region holds the start yet, for none of those reasons; where a
  link is in gestation, the detail gives its target and its executions and successes so far: a
  chain still growing when the episodes ran out shows few executions, a link that hardly ever
  reaches its target thousands with a success or two (the medium maze's MF-DSC++ seed 5 of
  ``runs_her_future/``: 4,029 executions, 1 success); runs that log
  ``options/gestation_fail_distance`` also say how far from its target its failed executions
  started, on average (and its successful ones);
- ``unfinished``: the run has no ``eval.json`` yet (stopped or still training before its final
  evaluation); its row shows what ``metrics.csv`` holds (episodes, in-band success, coverage) and
  the means leave it out of the final success;
- ``decayed`` (before any of the above): the in-band evaluation reached ``SOLVED`` at some point
  of training (column "best in-band") and neither its last window nor the final evaluation
  is there any more: a chain that worked stopped working well before the end (when only the
  final evaluation fell, the verdict is ``broke late``);
- ``broke late`` (before any of the above): the in-band evaluation's last window
  (``inband/success_rate``, episodes that began in about the last 20-40 iterations) was at or
  above ``SOLVED`` and the final evaluation is below it by more than ``LATE_DROP`` (over three
  standard errors of a 32- against a 100-episode estimate near 0.9): a chain that worked scored
  lower at the end. The in-band window lags the policy (a failed episode takes the full episode
  length to finish, about 20 iterations on the ant) and smooths it, so it misses short dips;
  periodic evaluations (``eval_every``) of the ant's medium maze show chains whose newest link,
  at the start, fails for 10-20 iterations and recovers.

With periodic evaluations in ``metrics.csv`` the reading also counts how many of them, once one
had reached ``SOLVED``, fell below ``DIP`` (column "dips once solved"): a chain that dips is one
whose final evaluation is partly luck.

Column "coverage lost": from the first iteration at which some option's region held the start
(``options/start_covered``), how many times it then stopped holding it, with the links the chain
made from that first iteration on ("3 (+7 links)"). The chain grows whenever the start is not
covered, so each loss can add a link at the start. Losses alone are no verdict: chains that
succeed lose the start too.

Column "fading links": from ``options.csv`` (the option table every few iterations), the mature
links whose training executions succeed much less often at the end than they once did: each
link's executions since it matured are cut into spans of at least ``FADE_SPAN`` executions, and
a link fades when its best span's success rate was at least ``FADE_BEST`` and its last span's
is lower by ``FADE_DROP`` or more ("7 (0.85 to 0.21)"). A chain that decays names the links it
lost there. Runs from before ``options.csv`` show "-".

Only the lean files are read (no checkpoint), so it works on results copied off a GPU host.
``python -m dscpp_jax.cli diagnose RUN_OR_GROUP_DIR ...`` prints one row per seed.
"""
from __future__ import annotations

import collections
import csv
import json
import math
import os
from typing import Optional, Sequence

from dscpp_jax.host_loop import STALLED_LINK_EXECUTIONS, link_stalled  # noqa: F401 (re-exported)
from dscpp_jax.options import GLOBAL, MATURE, STATUS_NAMES
from dscpp_jax.run_dir import is_group_dir, seed_dirs
from dscpp_jax.run_logging import OPTIONS_FILE

SOLVED = 0.8              # success from the start at or above this: nothing to diagnose
WEAK_LINK = 0.2           # an option that succeeds in fewer of its evaluation executions is weak
LATE_DROP = 0.2           # broke late: the final evaluation this far below the in-band window
FALLS_SHARE = 0.5         # falls: at least this share of the failed evaluation episodes
DIP = 0.5                 # a periodic evaluation below this, after one reached SOLVED, is a dip
FADE_SPAN = 40            # fading links: executions per span of a link's success rate
FADE_BEST = 0.5           # ... whose best span succeeded at least this often
FADE_DROP = 0.3           # ... and whose last span succeeds this much less often

COLUMNS = ("run", "success", "in-band at the end", "best in-band", "dips once solved",
           "start covered", "coverage lost", "options", "falls", "weak links", "fading links",
           "verdict")


def _start_distances(metrics: dict) -> str:
    """"; failures started D from its target (successes S)" for the link in gestation, from
    ``options/gestation_fail_distance`` and ``options/gestation_success_distance`` (the mean
    straight-line distance of its stored failed and successful starts to its target's nearest
    positive state); "" where the run does not log them (older runs) or they are undefined."""
    fail = _num(metrics, "options/gestation_fail_distance")
    succ = _num(metrics, "options/gestation_success_distance")
    if not math.isfinite(fail):
        return ""
    out = f"; failures started {fail:.1f} from its target"
    return out + (f" (successes {succ:.1f})" if math.isfinite(succ) else "")


def _last_row(path: str) -> dict:
    last = None
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            last = row
    if last is None:
        raise ValueError(f"{path} has no rows: the run has not finished an iteration")
    return last


def dips(path: str) -> Optional[tuple]:
    """(dips, evaluations) of a ``metrics.csv``'s periodic evaluations from the first that
    reached ``SOLVED`` on: how many of those (the first included) fell below ``DIP``. (0, 0) when
    none reached ``SOLVED``; None when the run logged fewer than two periodic evaluations."""
    vals = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            v = _num(row, "eval/success_rate")
            if math.isfinite(v):
                vals.append(v)
    if len(vals) < 2:
        return None
    first = next((i for i, v in enumerate(vals) if v >= SOLVED), None)
    if first is None:
        return (0, 0)
    after = vals[first:]
    return (sum(v < DIP for v in after), len(after))


def best_inband(path: str) -> float:
    """The highest in-band success (``inband/success_rate``) of a ``metrics.csv``'s rows; NaN
    when it logs none."""
    best = math.nan
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            v = _num(row, "inband/success_rate")
            if math.isfinite(v) and not v <= best:
                best = v
    return best


def coverage_lost(path: str) -> Optional[tuple]:
    """(losses, links) of a ``metrics.csv``: from the first row whose ``options/start_covered``
    is set, how many later rows clear it after a row that had it set, and how much
    ``options/num_options`` grew from that first row to the last. None when the start was never
    covered."""
    covered, options = [], []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            c = _num(row, "options/start_covered")
            if math.isfinite(c):
                covered.append(c > 0.5)
                options.append(_num(row, "options/num_options", 0.0))
    first = next((i for i, c in enumerate(covered) if c), None)
    if first is None:
        return None
    losses = sum(1 for a, b in zip(covered[first:], covered[first + 1:]) if a and not b)
    return losses, int(options[-1] - options[first])


def link_spans(path: str) -> dict:
    """{option: [(first iteration, last iteration, executions, success rate), ...]} of an
    ``options.csv``: each mature link's executions from the snapshot where it was first mature
    on, cut into consecutive spans of at least ``FADE_SPAN`` executions (a last, shorter
    remainder is dropped). A row's counters restarting (the row freed and reused by another
    link) start its spans over."""
    snaps: dict = collections.defaultdict(list)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            if row.get("status") != STATUS_NAMES[MATURE] or int(row["option"]) == GLOBAL:
                continue   # the chain's links: the goal option and its descendants
            snaps[int(row["option"])].append((int(row["iteration"]), int(row["executions"]),
                                              int(row["successes"])))
    out = {}
    for k, s in snaps.items():
        spans, (it0, e0, s0) = [], s[0]
        for it, e, n in s[1:]:
            if e < e0:           # a new link in this row
                spans, (it0, e0, s0) = [], (it, e, n)
                continue
            if e - e0 >= FADE_SPAN:
                spans.append((it0, it, e - e0, (n - s0) / (e - e0)))
                it0, e0, s0 = it, e, n
        out[k] = spans
    return out


def fading_links(run_dir: str) -> Optional[list]:
    """[(option, best span's success rate, last span's), ...] of a run's mature links that fade
    (see the module docstring), most faded first; None when the run has no ``options.csv``."""
    path = os.path.join(run_dir, OPTIONS_FILE)
    if not os.path.isfile(path):
        return None
    out = []
    for k, spans in link_spans(path).items():
        if len(spans) < 2:
            continue
        best, last = max(r for *_, r in spans), spans[-1][3]
        if best >= FADE_BEST and last <= best - FADE_DROP:
            out.append((k, best, last))
    return sorted(out, key=lambda t: (t[2] - t[1], t[0]))


def _num(d: dict, key: str, default: float = math.nan) -> float:
    try:
        v = float(d.get(key, default))
    except (TypeError, ValueError):
        return default
    return v


def diagnose_run(run_dir: str) -> dict:
    """One run's reading: success, coverage, falls, weak links and the verdict (see the module
    docstring). A run without ``eval.json`` gets the verdict ``unfinished`` and a NaN success.
    Raises ValueError naming what is missing when the directory holds no ``metrics.csv``, or
    when that has no skill-chain columns (flat learners)."""
    paths = {n: os.path.join(run_dir, n) for n in ("metrics.csv", "eval.json", "config.json")}
    if not os.path.isfile(paths["metrics.csv"]):
        raise ValueError(f"{run_dir}: no metrics.csv; diagnose reads a run's metrics.csv and "
                         f"eval.json (a seed's directory, or a group directory for all its "
                         f"seeds)")
    last = _last_row(paths["metrics.csv"])
    if "options/start_covered" not in last:
        raise ValueError(f"{run_dir}: metrics.csv has no options/* columns; diagnose reads the "
                         f"skill chain of DSC, dual, MF-DSC++ or MB-DSC++ runs")
    finished = os.path.isfile(paths["eval.json"])
    ev = {}
    if finished:
        with open(paths["eval.json"]) as f:
            ev = json.load(f)
    episodes = math.nan
    if os.path.isfile(paths["config.json"]):
        with open(paths["config.json"]) as f:
            episodes = float(json.load(f).get("config", {}).get("eval_episodes", math.nan))
    success = _num(ev, "eval/success_rate")
    inband = _num(last, "inband/success_rate")
    covered = _num(last, "options/start_covered") > 0.5
    full = _num(last, "options/capacity_hit") > 0.5
    g_exec = _num(last, "options/gestation_executions", 0.0)
    g_parent = int(_num(last, "options/gestation_parent", -1.0))
    g_succ = _num(last, "options/gestation_successes", 0.0)
    stalled = link_stalled(last)
    falls = _num(ev, "eval/flipped_failures")
    failures = (round((1.0 - success) * episodes)
                if math.isfinite(episodes) and math.isfinite(success) else math.nan)
    weak = sorted(int(k.rsplit("/", 1)[1]) for k, v in ev.items()
                  if k.startswith("eval/option_success/") and int(k.rsplit("/", 1)[1]) > 0
                  and isinstance(v, (int, float)) and math.isfinite(v) and v < WEAK_LINK)
    if not finished:
        verdict = (f"unfinished ({int(_num(last, 'episodes', 0.0))} episodes, start "
                   f"{'covered' if covered else 'not covered'}, no final evaluation)")
    elif success >= SOLVED:
        verdict = "solved"
    elif covered:
        parts = []
        if failures and math.isfinite(falls) and falls >= FALLS_SHARE * failures:
            parts.append("falls")
        if weak:
            parts.append("weak link" + ("s" if len(weak) > 1 else "") + " "
                         + ", ".join(str(w) for w in weak))
        verdict = "; ".join(parts) or "start covered, failing on the way"
    elif full:
        verdict = "table full"
    elif stalled:
        verdict = (f"stalled link (targets option {g_parent}, {int(g_exec)} executions"
                   f"{_start_distances(last)})")
    elif g_exec > 0:
        verdict = (f"not covered (link in gestation towards option {g_parent}: {int(g_exec)} "
                   f"executions, {int(g_succ)} success{'' if int(g_succ) == 1 else 'es'}"
                   f"{_start_distances(last)})")
    else:
        verdict = "not covered"
    best = best_inband(paths["metrics.csv"])
    if (success < SOLVED and math.isfinite(inband) and inband >= SOLVED
            and success < inband - LATE_DROP):
        verdict = f"broke late ({verdict})"
    elif (finished and success < SOLVED and math.isfinite(best) and best >= SOLVED
          and math.isfinite(inband) and inband < SOLVED):
        verdict = f"decayed ({verdict})"
    return {"run": run_dir, "success": success, "inband": inband, "best_inband": best,
            "dips": dips(paths["metrics.csv"]), "start_covered": covered,
            "coverage_lost": coverage_lost(paths["metrics.csv"]),
            "options": int(_num(last, "options/num_options", 0.0)), "table_full": full,
            "falls": falls, "failures": failures, "weak_links": weak, "stalled_link": stalled,
            "fading_links": fading_links(run_dir), "verdict": verdict}


def chain_verdict(cfg, run_dir: str) -> Optional[str]:
    """The verdict of :func:`diagnose_run` for a finished run with a skill chain (None for flat
    learners, when the run left no eval.json, or when its files cannot be read)."""
    if not cfg.hierarchical or not os.path.isfile(os.path.join(run_dir, "eval.json")):
        return None
    try:
        return diagnose_run(run_dir)["verdict"]
    except (ValueError, OSError):
        return None


def diagnose(run_dirs: Sequence[str]) -> list:
    """:func:`diagnose_run` of every run; a seed group's directory stands for its seeds."""
    out = []
    for d in run_dirs:
        if os.path.isdir(d) and is_group_dir(d):
            out += [diagnose_run(s) for s in seed_dirs(d)]
        else:
            out.append(diagnose_run(d))
    return out


def format_table(rows: Sequence[dict], root: Optional[str] = None) -> str:
    """A Markdown table of :func:`diagnose` rows (run paths relative to ``root``)."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        run = os.path.relpath(r["run"], root) if root else r["run"]
        falls = ("-" if not math.isfinite(r["falls"]) else
                 f"{int(r['falls'])} of {int(r['failures'])}" if math.isfinite(r["failures"])
                 else f"{int(r['falls'])}")
        inband = r.get("inband", math.nan)
        best = r.get("best_inband", math.nan)
        dip = r.get("dips")
        success = f"{r['success']:.2f}" if math.isfinite(r["success"]) else "-"
        lost = r.get("coverage_lost")
        if lost is None:
            lost = "-"
        else:
            n, links = lost
            lost = f"{n}" + (f" (+{links} link{'' if links == 1 else 's'})" if links else "")
        cells = [run, success, f"{inband:.2f}" if math.isfinite(inband) else "-",
                 f"{best:.2f}" if math.isfinite(best) else "-",
                 "-" if not dip or not dip[1] else f"{dip[0]} of {dip[1]}",
                 "yes" if r["start_covered"] else "no", lost,
                 f"{r['options']}" + (" (full)" if r["table_full"] else ""), falls,
                 ", ".join(map(str, r["weak_links"])) or "-",
                 "-" if not r.get("fading_links") else
                 ", ".join(f"{k} ({b:.2f} to {a:.2f})" for k, b, a in r["fading_links"]),
                 r["verdict"]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdict_kind(verdict: str) -> str:
    """The verdict without its details: "weak links 3, 7" -> "weak link", "broke late (falls)"
    -> "broke late", "decayed (weak link 4)" -> "decayed", "stalled link (targets option 15, ...)" -> "stalled link", "falls; weak
    link 7" -> "falls and weak link"."""
    parts = [p.strip() for p in verdict.split(" (", 1)[0].split(";")]
    return " and ".join("weak link" if p.startswith("weak link") else p for p in parts)


def format_summary(rows: Sequence[dict]) -> str:
    """One line: how many runs got each kind of verdict, most common first (ties by name), the
    count before the kind and the kinds apart by semicolons, since a kind may hold a comma
    ("5 runs: 2 solved; 1 falls and weak link; 1 start covered, failing on the way; ...")."""
    counts = collections.Counter(verdict_kind(r["verdict"]) for r in rows)
    parts = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
    return f"{len(rows)} runs: " + "; ".join(f"{n} {k}" for k, n in parts)


def mean_se(values: Sequence[float]) -> Optional[tuple]:
    """(mean, standard error, count) of the finite values; None when there are none."""
    v = [float(x) for x in values if math.isfinite(float(x))]
    if not v:
        return None
    m = sum(v) / len(v)
    se = (math.sqrt(sum((x - m) ** 2 for x in v) / (len(v) - 1) / len(v))
          if len(v) > 1 else 0.0)
    return m, se, len(v)


def format_means(rows: Sequence[dict]) -> str:
    """One line: mean ± standard error over the runs of the final evaluation's success from the
    start and of the in-band success at the end of training (runs without in-band evaluation
    left out of the second, with their number said)."""
    out = []
    for key, name in (("success", "success from the start"), ("inband", "in-band at the end")):
        ms = mean_se([r.get(key, math.nan) for r in rows])
        if ms is None:
            out.append(f"{name} -")
        else:
            m, se, n = ms
            out.append(f"{name} {m:.2f} ± {se:.2f}" + (f" ({n} of {len(rows)} runs)"
                                                         if n < len(rows) else ""))
    return ", ".join(out)

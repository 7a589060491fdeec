"""Reproduce the paper's comparisons: train what a figure needs as seed groups, then write each
figure as PNG, the numbers behind it as CSV, and a README that checks every claim of the paper
against what was measured.

    python experiments/reproduce.py --fig 6                      # or: make reproduce FIG=6
    python experiments/reproduce.py --fig all --time-budget 3600 # re-run the same command: goes on
    python experiments/reproduce.py --fig 5,A3 --report-only     # figures + README from what exists
    # a CPU smoke run on point-mass twins
    python experiments/reproduce.py --fig 6,5,A2,A3 --env-map u_maze=point_u_maze \\
        --mazes u_maze --algos dsc,mf_dscpp --seeds 0-1 --episodes 40 \\
        --runs-root /tmp/r --out /tmp/o

    # the train commands of the groups still to train, to run side by side on one GPU
    python experiments/reproduce.py --fig 5,6,A2,A3 --print-commands --time-budget 3000

One `train --seeds` program per (algorithm, env, subgoal, seeds), in a group directory named
after them under --runs-root (no time stamp; `-long` for the 12,000-episode TD3, `-a1` for
appendix Figure 1's own runs, `-optcritic` for appendix Figure 2's one critic per option,
`-paperrule` for a group with the preset's settings beyond the paper turned off), so that
the next call finds it; figures that need the same group (MF-DSC++ on U-maze: Figures 5, 6, A2,
A3) share it, trained once. A group whose seeds have all reached the schedule is skipped, one
with a checkpoint is continued with `train --resume` (also to a longer --episodes), one without
a checkpoint (killed before its first) is moved aside and started again. Where no group of
exactly the asked seeds exists, a figure takes them from the smallest larger group of the same
algorithm, env, subgoal and tag (seeds 0-4 of `medium-mf_dscpp-g0-14`). A group made with other
settings (--set, --preset) is left alone, with a message, and the README lists it with the
settings that differ. `--time-budget` bounds each train call
(it checkpoints and stops) and `--stop-after` the whole call, for jobs with a wall-clock limit
(calls still waiting for a GPU get what is left; none starts with less than `--min-call`); the
figures are drawn from whatever has been trained, and the README
marks claims whose runs have not finished.

Protocol (defaults, as in the paper): 5 seeds, 2,001 episodes of at most 1,000 steps (the
preset's episode length), success from the task start, mean and standard error over seeds.
Figures 5, 6, A2 and A3 compare the learners at the paper's rule: where the preset gives DSC++
settings beyond the paper (the chain's frontier, the medium maze's model-free TD3), their groups
turn them off (`-paperrule`, `dscpp_jax.config.paper_rule_overrides`; a group of the preset's own
name made without them serves too); the paper's baselines have none in any preset. Figure 6
shows the preset's DSC++ groups with those settings on in panels of their own, titled "DSC++
beyond the paper", drawn where they exist (`--beyond-paper` trains them).
Figure 4 and appendix Figure 1 train on Ant-Reacher for 1,000 episodes; Figure 6's dashed line
is TD3+HER after 12,000 episodes (`--long-td3` schedules it). Appendix Figure 2 compares MF-DSC++
on U-maze with its one shared critic (Figure 5's and 6's group) and with one TD3 actor and critic
per option (`--set shared_critic=false`).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from dscpp_jax import diagnose, envs, svm
from dscpp_jax.cli import (
    deterministic_choice, load_run, parse_overrides, use_compile_cache, use_xla_flags)
from dscpp_jax.config import (
    Config, DSCPP_ALGOS, HIERARCHICAL_ALGOS, MEDIUM_MODEL_FREE_TD3, PAPER_BASELINES,
    paper_rule_overrides, preset)
from dscpp_jax.evaluate import evaluate
from dscpp_jax.group_train import seed_dirs as all_seed_dirs
from dscpp_jax.plots import draw_maze, maze_layout, metric_curve
from dscpp_jax.run_logging import load_config, read_metrics
from dscpp_jax.seed_group import format_seeds, parse_seeds

FIGS = ("4", "5", "6", "A1", "A2", "A3")
MAZES = ("u_maze", "medium", "four_rooms")
FIG6_ALGOS = ("td3_her", "mb_flat", "mb_flat_value", "dsc", "mf_dscpp", "mb_dscpp")
FIG5_ALGOS = ("dsc", "dual", "mf_dscpp", "mb_dscpp")
A3_ALGOS = FIG5_ALGOS
NAMES = {"td3_her": "TD3+HER", "mb_flat": "MB flat", "mb_flat_value": "MB flat + value",
         "dsc": "DSC", "dual": "DSC + dual classifiers", "mf_dscpp": "MF-DSC++",
         "mb_dscpp": "MB-DSC++"}
# one colour per algorithm in every panel of a figure (tab10 in the order of NAMES)
COLORS = {a: f"C{i}" for i, a in enumerate(NAMES)}
CORNERS = ((9.0, 9.0), (-9.0, 9.0), (9.0, -9.0), (-9.0, -9.0))
# appendix Figure 2's second arm: one TD3 actor + twin critic per option slot (model-free only)
A2_SETS = ("shared_critic=false",)
# Config fields that `train --resume` accepts (schedule and host-side cadences)
RESUME_FIELDS = {"total_env_steps", "total_episodes", "eval_every", "eval_episodes",
                 "checkpoint_every", "keep_checkpoints"}
# Settings every group of the driver trains with, before the user's --set: the committed paper
# runs were trained with float32 TD3, which the ant preset no longer uses for the model-free
# learners, so a group trained or retrained by the driver matches the others in its figures.
PAPER_SETS = ("td3_dtype=float32",)
# ... and per env: the committed ant U-maze groups planned with 4,096 MPC samples per decision,
# which the preset lowered to 2,048 there.
PAPER_ENV_SETS = {"u_maze": ("mpc_samples=4096",)}


# ------------------------------------------------------------------------------------------------
# Experiments
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Exp:
    """One seed group: a paper env (before --env-map), an algorithm, a subgoal rule, a schedule."""
    env: str
    algo: str
    episodes: int
    seeds: str
    subgoal: str = "robust"
    tag: str = ""              # "" | "long" (Fig. 6's 12,000-episode TD3) | "a1" (A1's own)
    #                            | "optcritic" (A2's one critic per option) | "paperrule" (the
    #                            preset's settings beyond the paper turned off)
    sets: tuple = ()           # extra --set values of this group
    beyond: bool = False       # drawn as beyond the paper (the preset's extras on), not claimed

    def run_env(self, env_map: dict) -> str:
        return env_map.get(self.env, self.env)

    def name(self, env_map: dict) -> str:
        sub = "-dp" if self.subgoal == "dp" else ""
        tag = f"-{self.tag}" if self.tag else ""
        seeds = format_seeds(parse_seeds(self.seeds))
        return f"{self.run_env(env_map)}-{self.algo}{sub}-g{seeds}{tag}"


def _csv_list(text: Optional[str], default) -> tuple:
    if not text:
        return tuple(default)
    return tuple(t.strip() for t in text.split(",") if t.strip())


def parse_figs(text: str) -> tuple:
    out = []
    for f in _csv_list(text, FIGS):
        f = f.upper()
        if f == "ALL":
            out.extend(FIGS)
            continue
        if f not in FIGS:
            raise ValueError(f"unknown figure {f!r}; choose from {', '.join(FIGS)} or all")
        out.append(f)
    return tuple(dict.fromkeys(out))


def _set_text(value) -> str:
    """A Config value as `--set` writes it."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def paper_rule_sets(maze: str, algo: str, args) -> tuple:
    """The --set pairs that train `algo` on `maze` (after --env-map) at the paper's rule: the
    preset's settings beyond the paper turned off (`config.paper_rule_overrides`: the chain's
    frontier, the medium maze's model-free TD3); () where the preset adds none."""
    over = paper_rule_overrides(args.preset, args.env_map.get(maze, maze), algo)
    return tuple(f"{k}={_set_text(v)}" for k, v in over.items())


def paper_exp(maze: str, algo: str, episodes: int, seeds: str, args, tag: str = "",
              sets: tuple = ()) -> Exp:
    """The group of `algo` on `maze` at the paper's rule: the preset's own group where the preset
    adds nothing beyond the paper there, else one tagged `paperrule` with those extras off."""
    off = paper_rule_sets(maze, algo, args)
    if off:
        tag = "paperrule" + (f"-{tag}" if tag else "")
    return Exp(maze, algo, episodes, seeds, tag=tag, sets=off + tuple(sets))


def plan(args) -> dict:
    """{figure: [Exp, ...]} for the requested figures. Figures 5, 6, A2 and A3 compare the
    learners at the paper's rule (`paper_exp`); Figure 6 also shows DSC++ with the preset's
    settings beyond the paper, where it has some, in panels of their own (`Exp.beyond`)."""
    figs = parse_figs(args.fig)
    algos = set(_csv_list(args.algos, FIG6_ALGOS + ("dual",)))
    mazes = _csv_list(args.mazes, MAZES)
    out: dict[str, list] = {}
    ep, seeds = args.episodes, args.seeds
    if "6" in figs:
        out["6"] = [paper_exp(m, a, ep, seeds, args) for m in mazes for a in FIG6_ALGOS
                    if a in algos]
        out["6"] += [Exp(m, a, ep, seeds, beyond=True) for m in mazes for a in DSCPP_ALGOS
                     if a in algos and paper_rule_sets(m, a, args)]
        if args.long_td3:
            out["6"].append(Exp("u_maze", "td3_her", args.long_td3_episodes,
                                args.long_td3_seeds or seeds, tag="long"))
    if "5" in figs:
        out["5"] = [paper_exp("u_maze", a, ep, seeds, args) for a in FIG5_ALGOS if a in algos]
    if "A3" in figs:
        out["A3"] = [paper_exp("u_maze", a, ep, seeds, args) for a in A3_ALGOS if a in algos]
    # Appendix Figure 1 needs checkpoints from early in training: its groups save one every
    # --a1-every iterations and keep them all (--a1-keep). With --a1-seeds equal to --seeds it
    # shares Figure 4's groups, which then do the same; otherwise it trains its own (by default
    # one seed, as the figure shows one run).
    keep = (f"keep_checkpoints={args.a1_keep}", f"checkpoint_every={args.a1_every}")
    share = parse_seeds(args.a1_seeds) == parse_seeds(seeds)
    fig4 = [Exp("ant_reacher", args.fig4_algo, args.fig4_episodes, seeds, subgoal=s,
                sets=keep if share else ()) for s in ("robust", "dp")]
    if "4" in figs:
        out["4"] = fig4
    if "A1" in figs:
        out["A1"] = [Exp("ant_reacher", "dsc", args.fig4_episodes, args.a1_seeds,
                         tag="" if share else "a1", sets=keep)]
        if args.fig4_algo != "dsc":
            out["A1"].append(fig4[0] if share else Exp("ant_reacher", args.fig4_algo,
                                                       args.fig4_episodes, args.a1_seeds,
                                                       tag="a1", sets=keep))
    # Appendix Figure 2: MF-DSC++ on U-maze, shared critic (the very group of Figures 5 and 6,
    # trained once) vs one critic per option (its own group, `-optcritic`)
    if "A2" in figs and "mf_dscpp" in algos:
        out["A2"] = [paper_exp("u_maze", "mf_dscpp", ep, seeds, args),
                     paper_exp("u_maze", "mf_dscpp", ep, seeds, args, tag="optcritic",
                               sets=A2_SETS)]
    return out


# ------------------------------------------------------------------------------------------------
# Group state on disk (no JAX)
# ------------------------------------------------------------------------------------------------
def _overrides(pairs) -> dict:
    """`--set name=value` pairs as the training command line reads them."""
    return parse_overrides(list(pairs))


def say(msg: str, flush: bool = True) -> None:
    """One line to stdout in a single write: train calls report from several threads at once."""
    sys.stdout.write(msg + "\n")
    if flush:
        sys.stdout.flush()


def group_dir(exp: Exp, args) -> str:
    """Where an experiment's group lives under --runs-root: the directory named after it
    (`Exp.name`) when there is one; else the smallest group of the same env, algorithm, subgoal
    rule and tag whose seeds include the asked ones (seeds 0-4 of a 15-seed group
    `medium-mf_dscpp-g0-14`: the seeds of a group are independent runs, so a figure may take
    some of them); else the named path, where a new group trains."""
    path = os.path.join(args.runs_root, exp.name(args.env_map))
    if os.path.exists(path):
        return path
    if exp.tag.startswith("paperrule"):
        # a group of the preset's own name made without the settings beyond the paper (before
        # the preset had them) is the paper's rule's group
        plain = dataclasses.replace(exp, tag=exp.tag[len("paperrule"):].lstrip("-"))
        found = group_dir(plain, args)
        if os.path.isfile(os.path.join(found, "group.json")):
            try:
                if not config_mismatch(found, exp, args):
                    return found
            except (OSError, ValueError, KeyError, TypeError):
                pass
    want = set(parse_seeds(exp.seeds))
    sub = "-dp" if exp.subgoal == "dp" else ""
    tag = f"-{exp.tag}" if exp.tag else ""
    pattern = re.compile(re.escape(f"{exp.run_env(args.env_map)}-{exp.algo}{sub}-g")
                         + r"[0-9][0-9,\-]*" + re.escape(tag) + "$")
    try:
        names = sorted(os.listdir(args.runs_root))
    except OSError:
        return path
    best = None
    for d in names:
        seeds = _group_seeds(os.path.join(args.runs_root, d)) if pattern.match(d) else None
        if seeds is not None and want <= set(seeds) and (best is None or len(seeds) < best[0]):
            best = (len(seeds), d)
    return os.path.join(args.runs_root, best[1]) if best else path


def _group_seeds(gdir: str) -> Optional[list]:
    """The sorted seeds a group directory's group.json names; None where it cannot be read."""
    try:
        with open(os.path.join(gdir, "group.json")) as f:
            return sorted(int(x) for x in json.load(f)["seeds"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def shown_name(exp: Exp, gdir: str) -> str:
    """A group's directory name for the README (in backticks), with the seeds taken from it
    where it holds more."""
    name = os.path.basename(os.path.normpath(gdir))
    have = _group_seeds(gdir)
    want = sorted(parse_seeds(exp.seeds))
    return f"`{name}`" + ("" if have is None or want == have
                          else f" (seeds {format_seeds(want)} of it)")


def checkpoint_steps(group_dir: str) -> list:
    d = os.path.join(group_dir, "checkpoints")
    if not os.path.isdir(d):
        return []
    return sorted(int(s) for s in os.listdir(d) if s.isdigit())


def seed_dirs(group_dir: str) -> list:
    """The seed directories of a group that have logged at least one iteration."""
    try:
        dirs = all_seed_dirs(group_dir)
    except (OSError, ValueError, KeyError):
        return []
    return [d for d in dirs if os.path.isfile(os.path.join(d, "metrics.csv"))]


def _last_row(run_dir: str) -> Optional[dict]:
    try:
        m = read_metrics(run_dir)
    except (OSError, ValueError):
        return None
    if not m.get("iteration"):
        return None
    return {k: v[-1] for k, v in m.items()}


def _sets(exp: Exp, args) -> list:
    """The --set pairs of one group: the driver's own, the user's, the experiment's (later wins)."""
    own = list(PAPER_SETS) + list(PAPER_ENV_SETS.get(exp.run_env(args.env_map), ()))
    return own + list(args.set) + list(exp.sets)


def schedule(exp: Exp, args) -> tuple:
    """(total_episodes, total_env_steps): the episode budget binds; the step cap is loose enough
    for it ((episodes + num_envs) x episode length) unless --total-steps gives one."""
    kw = _overrides(_sets(exp, args))
    kw.pop("total_env_steps", None)
    cfg = preset(args.preset, exp.run_env(args.env_map), exp.algo, **kw)
    steps = args.total_steps or (exp.episodes + cfg.run.num_envs) * cfg.task.episode_length
    return exp.episodes, int(steps)


def group_state(group_dir: str, sched: tuple) -> str:
    """new | stale (a directory without a checkpoint) | unfinished | finished."""
    if not os.path.isdir(group_dir):
        return "new"
    steps = checkpoint_steps(group_dir)
    if not os.path.isfile(os.path.join(group_dir, "group.json")):
        return "stale"
    with open(os.path.join(group_dir, "group.json")) as f:
        n = len(json.load(f)["seeds"])
    dirs = seed_dirs(group_dir)
    rows = [_last_row(d) for d in dirs]
    if len(dirs) < n or any(r is None for r in rows):
        return "unfinished"
    episodes, total = sched
    done = all(r["env_steps"] >= total or (episodes > 0 and r["episodes"] >= episodes)
               for r in rows)
    # train writes each seed's eval.json after its last checkpoint: a call killed after logging
    # an iteration but before saving it has an older (or no) eval.json, and is not done
    if done and all(_eval_iteration(d) == int(r["iteration"]) for d, r in zip(dirs, rows)):
        return "finished"     # also a lean copy (metrics, eval.json, no checkpoints)
    return "unfinished" if steps else "stale"


def _eval_iteration(seed_dir: str) -> Optional[int]:
    try:
        with open(os.path.join(seed_dir, "eval.json")) as f:
            return int(json.load(f)["iteration"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _listed(names) -> str:
    """'A', 'A and B', 'A, B and C'."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def beyond_words(maze: str, args) -> str:
    """What the preset adds beyond the paper for DSC++ on `maze`, in a few words ("" if
    nothing)."""
    over = {a: paper_rule_overrides(args.preset, args.env_map.get(maze, maze), a)
            for a in DSCPP_ALGOS}
    said = set().union(*over.values())
    words = []
    if {"frontier_start_prob", "frontier_parent"} & said:
        words.append("the chain's frontier")
    if "max_options" in said:
        words.append("more option rows")
    if "td3_updates_per_step" in over["mb_dscpp"]:
        words.append("MB-DSC++ more TD3 steps per transition")
    if set(MEDIUM_MODEL_FREE_TD3) & set(over["mf_dscpp"]):
        words.append("MF-DSC++ the medium maze's TD3")
    return ", ".join(words)


def _frontier_note(data, args) -> str:
    """Sentences for the protocol line on the preset's settings beyond the paper for the groups
    of this call: which groups turn them off to train at the paper's rule (tag `paperrule`,
    `dscpp_jax.config.paper_rule_overrides`), which are drawn with them on (Figure 6's panels
    "DSC++ beyond the paper"), and the ant preset's action penalty of the goal-conditioned
    model-free learners; "" where there is none."""
    exps = list(data.info)
    parts = []
    off = {}
    for e in exps:
        if e.tag.startswith("paperrule"):
            off.setdefault(e.name(args.env_map).split("-g")[0], paper_rule_sets(e.env, e.algo,
                                                                                args))
    if off:
        parts.append("At the paper's rule, the groups tagged `-paperrule` turn off the preset's "
                     "settings beyond the paper (`dscpp_jax.config.paper_rule_overrides`): "
                     + "; ".join(f"{k}: `{' '.join(v)}`" for k, v in off.items()) + ".")
    beyond = sorted({e.env for e in exps if e.beyond})
    if beyond:
        parts.append("Figure 6's panels \"DSC++ beyond the paper\" show the preset's own DSC++ "
                     "groups, with them on ("
                     + "; ".join(f"{m}: {beyond_words(m, args)}" for m in beyond)
                     + "; `docs/presets.md`); they are not claims of the paper.")
    penalty = sorted({e.algo for e in exps
                      if preset(args.preset, e.run_env(args.env_map), e.algo).td3.action_l2 > 0
                      and e.algo not in PAPER_BASELINES})
    if penalty:
        parts.append(f"{_listed([NAMES[a] for a in penalty])} keep the preset's action penalty "
                     "(`td3_action_l2`, OpenAI Baselines' HER); the paper's baselines have none.")
    return (" " + " ".join(parts)) if parts else ""


def _mismatch_or_error(group_dir: str, exp: Exp, args) -> list:
    """`config_mismatch`, or one line saying why the group's config could not be read."""
    try:
        return config_mismatch(group_dir, exp, args)
    except (OSError, ValueError, KeyError, TypeError) as e:
        return [f"config unreadable ({e})"]


def mismatch_lines(data, args) -> list:
    """One line per group on disk that was made with other settings than this call would train
    it with (`config_mismatch`): the figures draw it as made, and the training leaves it as it
    is, so the README says so. (A group that Figure 6's panels beyond the paper do not draw, made
    without those settings, is not listed for them.)"""
    out = []
    for exp, info in data.info.items():
        if not os.path.exists(os.path.join(info["dir"], "group.json")) or exp.beyond:
            continue
        try:
            bad = config_mismatch(info["dir"], exp, args)
        except (OSError, ValueError, KeyError, TypeError) as e:
            bad = [f"config unreadable ({e})"]
        if bad:
            out.append(f"- {info['name']}: " + "; ".join(bad))
    return out


def config_mismatch(group_dir: str, exp: Exp, args) -> list:
    """Fields the group was made with that differ from what this call would train it with: the
    preset of this version with the driver's, the user's and the experiment's --set pairs. A
    field the group's config lacks (added since) counts at its default, which is what the group
    ran with; so a group made before a preset changed is told apart from one made after. Not
    compared: the schedule and bookkeeping fields a resumed call may change (RESUME_FIELDS), the
    seed (the group's seeds are its own), the physics back end `auto` resolved to on the
    training host unless --set names it, and fields without effect in both configs
    (`Config.inert_fields`)."""
    with open(os.path.join(group_dir, "group.json")) as f:
        have = json.load(f)["config"]
    kw = _overrides(_sets(exp, args))
    kw.update(subgoal=exp.subgoal)
    skip = set(RESUME_FIELDS) | {"seed"} | ({"physics"} if "physics" not in kw else set())
    asked = preset(args.preset, exp.run_env(args.env_map), exp.algo, **kw)
    made = Config.from_dict(have)   # fields added since: what it ran with
    skip |= asked.inert_fields() & made.inert_fields()   # e.g. the radius of a frontier left off
    want = {k: v for k, v in asked.flat().items() if k not in skip}
    had = made.flat()
    return [f"{k}={had[k]!r} (asked: {v!r})" for k, v in sorted(want.items()) if had[k] != v]


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------
def call_budget(args) -> Optional[float]:
    """Seconds the next train call's loop may run: --time-budget, cut to what is left of
    --stop-after (None: no limit)."""
    budget = args.time_budget
    if getattr(args, "deadline", None) is not None:
        left = args.deadline - time.time()
        budget = left if budget is None else min(budget, left)
    return budget


def train_command(exp: Exp, group_dir: str, args, resume: bool,
                  budget: Optional[float] = None) -> list:
    """The train call of one group; `budget`: its --time-budget (default: --time-budget)."""
    budget = args.time_budget if budget is None else budget
    episodes, total = schedule(exp, args)
    cmd = [sys.executable, "-m", "dscpp_jax.cli", "train"]
    sets = _sets(exp, args)
    if resume:
        cmd += ["--resume", group_dir]
        sets = [s for s in sets if s.split("=", 1)[0].strip().replace("-", "_") in RESUME_FIELDS]
    else:
        cmd += ["--env", exp.run_env(args.env_map), "--algo", exp.algo, "--seeds", exp.seeds,
                "--preset", args.preset, "--run-dir", group_dir]
        if exp.subgoal != "robust":
            cmd += ["--subgoal", exp.subgoal]
    cmd += ["--total-episodes", str(episodes), "--total-steps", str(total), "--no-progress"]
    for s in sets:
        if s.split("=", 1)[0].strip().replace("-", "_") not in ("total_env_steps",
                                                                 "total_episodes"):
            cmd += ["--set", s]
    if budget:
        cmd += ["--time-budget", f"{budget:g}"]
    if args.deterministic is not None:   # else train's default (dscpp_jax.cli.deterministic_default)
        cmd += ["--deterministic" if args.deterministic else "--no-deterministic"]
    if args.compile_cache:
        cmd += ["--compile-cache", args.compile_cache]
    return cmd


def train_one(exp: Exp, args, gpus, per_gpu: int = 1) -> str:
    """Train, continue or skip one group; returns its status word. `gpus`: a queue of GPU ids
    (or None) of which the call takes one; `per_gpu`: how many calls share each of them."""
    gdir = group_dir(exp, args)
    sched = schedule(exp, args)
    st = group_state(gdir, sched)
    named = os.path.join(args.runs_root, exp.name(args.env_map))
    if st in ("new", "stale") and gdir != named:   # a larger group with nothing to resume:
        gdir = named                               # train the asked seeds under their own name
        st = group_state(gdir, sched)
    name = os.path.basename(gdir)
    if st in ("finished", "unfinished"):
        bad = config_mismatch(gdir, exp, args)
        if bad:
            say(f"[reproduce] {name}: left as it is: the group was made with other settings "
                  f"({'; '.join(bad)}) and the figures show it as made. To train it with these "
                  f"settings, move {gdir} away or use another --runs-root", flush=True)
            return "mismatch"
    if st == "finished":
        say(f"[reproduce] {name}: skipped (finished)", flush=True)
        return "skipped"
    resume = st == "unfinished"
    cmd = train_command(exp, gdir, args, resume)
    shown = " ".join(["python"] + cmd[1:])
    if args.dry_run:
        say(f"[reproduce] {name}: would {'resume' if resume else 'start'}: {shown}", flush=True)
        return "dry-run"
    if st == "stale":
        aside = f"{gdir}.stale-{time.strftime('%Y%m%d-%H%M%S')}"
        shutil.move(gdir, aside)
        say(f"[reproduce] {name}: no checkpoint, moved aside to {aside}", flush=True)
    logs = os.path.join(args.runs_root, "logs")
    os.makedirs(logs, exist_ok=True)
    log = os.path.join(logs, f"{name}.log")
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    gpu = gpus.get() if gpus is not None else None
    budget = call_budget(args)      # taken when the call can start (it may have waited for a GPU)
    if getattr(args, "deadline", None) is not None and budget < args.min_call:
        if gpu is not None:
            gpus.put(gpu)
        say(f"[reproduce] {name}: not started: {max(budget, 0):.0f}s left of --stop-after, "
            f"under --min-call {args.min_call:.0f}s", flush=True)
        return "not started (--stop-after)"
    cmd = train_command(exp, gdir, args, resume, budget)
    shown = " ".join(["python"] + cmd[1:])
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(slot_gpus(gpu))
    share = per_gpu if gpu is not None else args.jobs
    if share > 1 and "XLA_PYTHON_CLIENT_MEM_FRACTION" not in env:
        # several calls on one GPU: each may take its share, not JAX's default 75 %
        env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{0.9 / share:.2f}"
    where = ("" if gpu is None else
             f" on GPU{'s' if '+' in gpu else ''} {','.join(slot_gpus(gpu))}")
    say(f"[reproduce] {name}: {'resumed' if resume else 'started'}{where} (log: {log})",
          flush=True)
    t0 = time.time()
    try:
        with open(log, "a") as f:
            f.write(f"\n== {time.strftime('%Y-%m-%d %H:%M:%S')} {shown}\n")
            f.flush()
            rc = subprocess.call(cmd, cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT)
    finally:
        if gpu is not None:
            gpus.put(gpu)
    dt = time.time() - t0
    if rc != 0:
        say(f"[reproduce] {name}: train FAILED (exit {rc}, {dt:.0f}s); see {log}", flush=True)
        return f"failed ({rc})"
    word = ("finished" if group_state(gdir, sched) == "finished"
            else "stopped at the time budget; run again to continue")
    say(f"[reproduce] {name}: {word} ({dt:.0f}s)", flush=True)
    return "resumed" if resume else "trained"


def pending_commands(args, figs: dict) -> list:
    """[(group name, state, command line or None)] for every group the figures need that has not
    reached its schedule: `python -m dscpp_jax.cli train ...` to start it (state "new") or to
    continue it (--resume; "unfinished"), each writing the directory the report reads. A group
    made with other settings ("mismatch") or a directory without a checkpoint ("stale") gets no
    command: move it away first. Finished groups are left out."""
    out = []
    exps = list(dict.fromkeys(e for es in figs.values() for e in es
                              if args.beyond_paper or not e.beyond))
    exps.sort(key=lambda e: e.tag == "long")
    names = {}
    for e in exps:
        names.setdefault(e.name(args.env_map), e)
    for name, exp in names.items():
        gdir = group_dir(exp, args)
        sched = schedule(exp, args)
        st = group_state(gdir, sched)
        named = os.path.join(args.runs_root, name)
        if st in ("new", "stale") and gdir != named:
            gdir = named
            st = group_state(gdir, sched)
        if st == "finished" and not config_mismatch(gdir, exp, args):
            continue
        if st in ("finished", "unfinished") and config_mismatch(gdir, exp, args):
            out.append((os.path.basename(gdir), "mismatch", None))
            continue
        if st == "stale":
            out.append((os.path.basename(gdir), "stale", None))
            continue
        cmd = train_command(exp, _shown_path(gdir), args, resume=st == "unfinished")
        out.append((os.path.basename(gdir), st, " ".join(["python"] + cmd[1:])))
    return out


def print_commands(args, figs: dict) -> int:
    """Print one train command per group still to train (`pending_commands`), with the memory
    share that lets them run side by side on one GPU; returns how many there are."""
    pend = pending_commands(args, figs)
    runnable = [p for p in pend if p[2]]
    share = "" if len(runnable) < 2 else \
        f"XLA_PYTHON_CLIENT_MEM_FRACTION={0.9 / len(runnable):.2f} "
    say(f"# {len(runnable)} group(s) to train for figure(s) {', '.join(figs)} under "
        f"{_shown_path(args.runs_root)} (run from {ROOT}; each line may run beside the others on "
        "one GPU, and again to continue after its --time-budget)")
    for name, st, cmd in pend:
        if cmd is None:
            why = ("made with other settings than this version's preset (see the README)"
                   if st == "mismatch" else "a directory without a checkpoint")
            say(f"# {name}: {why}; move it away to train it")
        else:
            say(f"# {name} ({'start' if st == 'new' else 'continue'})")
            say(share + cmd)
    return len(runnable)


def visible_gpus() -> list:
    """The GPUs this host shows a train call: CUDA_VISIBLE_DEVICES where it is set, else those
    `nvidia-smi -L` lists (none where it is missing)."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        ids = [g.strip() for g in env.split(",") if g.strip()]
        return [] if not ids or ids[0] == "-1" else ids
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True,
                             timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, _ in enumerate(l for l in out.splitlines() if l.startswith("GPU "))]


def check_gpus_allowed(gpus) -> None:
    """Where this process has CUDA_VISIBLE_DEVICES (a scheduler's share of the host), --gpus must
    name GPUs from it: each train call's CUDA_VISIBLE_DEVICES is set to its --gpus entry, so an
    entry outside the list would put the call on a GPU the job was not given."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is None:
        return
    allowed = visible_gpus()
    bad = [g for slot in gpus for g in slot_gpus(slot) if g not in allowed]
    if bad:
        raise ValueError(f"--gpus {','.join(gpus)}: {','.join(bad)} not in "
                         f"CUDA_VISIBLE_DEVICES={env}; name GPUs from that list "
                         f"(e.g. --gpus {','.join(allowed) or '<none visible>'})")


def slot_gpus(slot: str) -> list:
    """The GPUs of one --gpus entry: "2" is one GPU, "0+1+2+3" four GPUs that one train call
    gets together (its group's seeds are then split evenly over them)."""
    return [g.strip() for g in slot.split("+")]


def gpu_slots(gpus, jobs: int) -> list:
    """The GPU (or GPUs, "0+1") of each of `jobs` concurrent train calls, round robin over
    `gpus`: several calls share a GPU when there are more calls than GPUs (one group's physics is
    latency bound)."""
    gpus = list(gpus)
    if not gpus:
        raise ValueError("--gpus names no GPU")
    for slot in gpus:
        ids = slot_gpus(slot)
        if not all(g.isdigit() for g in ids) or len(set(ids)) < len(ids):
            raise ValueError(f"--gpus entry {slot!r}: write a GPU id (e.g. 2) or several joined "
                             "by + (e.g. 0+1+2+3) for one train call, each id once")
    return [gpus[j % len(gpus)] for j in range(max(1, jobs))]


def long_td3_seeds(args) -> Optional[str]:
    """The long TD3+HER group's seeds for the report: --long-td3-seeds, else those of the one
    such group in the runs root (it may have other seeds than --seeds), else None (--seeds)."""
    if args.long_td3_seeds or not args.runs_root or not os.path.isdir(args.runs_root):
        return args.long_td3_seeds
    pre = f"{args.env_map.get('u_maze', 'u_maze')}-td3_her-g"
    found = [d[len(pre):-len("-long")] for d in os.listdir(args.runs_root)
             if d.startswith(pre) and d.endswith("-long")]
    return found[0] if len(found) == 1 else None


def check_slot_sizes(figs: dict, slots: list, args) -> None:
    """A group split over several GPUs needs a multiple of their number of seeds (groups are
    never padded): say so before anything trains. Finished groups are only skipped."""
    env_map = args.env_map
    for e in dict.fromkeys(e for es in figs.values() for e in es
                           if args.beyond_paper or not e.beyond):
        if group_state(group_dir(e, args), schedule(e, args)) == "finished":
            continue
        n = len(parse_seeds(e.seeds))
        for slot in slots:
            k = len(slot_gpus(slot))
            if n % k:
                raise ValueError(f"{e.name(env_map)}: {n} seeds do not split evenly over the "
                                 f"{k} GPUs of --gpus entry {slot}; give that figure's groups a "
                                 f"multiple of {k} seeds (--seeds, --long-td3-seeds, "
                                 f"--a1-seeds) or fewer GPUs per entry")


def train_all(args, figs: dict) -> dict:
    """Train (or continue, or skip) every group the figures need, --jobs at a time (spread over
    the --gpus, round robin); {group name: status}."""
    exps = list(dict.fromkeys(e for es in figs.values() for e in es
                              if args.beyond_paper or not e.beyond))
    exps.sort(key=lambda e: e.tag == "long")   # the 12,000-episode TD3 run last
    names = {}
    for e in exps:   # groups of one directory (Figure 4's, shared with A1) train once
        names.setdefault(e.name(args.env_map), e)
    gpus, per_gpu = None, 1
    jobs = max(1, args.jobs)
    if args.gpus:
        slots = gpu_slots(_csv_list(args.gpus, ()), jobs)
        gpus = queue.Queue()
        for g in slots:
            gpus.put(g)
        per_gpu = max(slots.count(g) for g in slots)
    with ThreadPoolExecutor(jobs) as pool:
        futures = {n: pool.submit(train_one, e, args, gpus, per_gpu) for n, e in names.items()}
        return {n: f.result() for n, f in futures.items()}


# ------------------------------------------------------------------------------------------------
# Curves from metrics.csv
# ------------------------------------------------------------------------------------------------
def curves(dirs, column: str, x: str = "episodes", inband: bool = True) -> list:
    """One curve per run dir. Success from the start ("eval/success_rate") comes from the in-band
    evaluation (every iteration; the ant preset's default) where the runs have it, else from the
    periodic evaluations; ``inband=False`` keeps the evaluations' column (the final 100 episodes
    where evaluation runs only at the end)."""
    if inband and column == "eval/success_rate":
        cs = [c for c in (metric_curve(d, "inband/success_rate", x) for d in dirs) if c is not None]
        if cs:
            return cs
    return [c for c in (metric_curve(d, column, x) for d in dirs) if c is not None]


def mean_se(cs: list, max_points: int = 200):
    """(grid, mean, s.e., n) over curves on the union of their x values up to the shortest."""
    xmax = min(c[0][-1] for c in cs)
    grid = np.unique(np.concatenate([c[0][c[0] <= xmax] for c in cs]))
    if grid.size > max_points:
        grid = grid[np.linspace(0, grid.size - 1, max_points).round().astype(int)]
    ys = np.stack([np.interp(grid, c[0], c[1]) for c in cs])
    se = ys.std(0, ddof=1) / np.sqrt(len(cs)) if len(cs) > 1 else np.zeros_like(grid)
    return grid, ys.mean(0), se, len(cs)


def finals(cs: list) -> np.ndarray:
    return np.array([c[1][-1] for c in cs])


def final_evals(dirs, column: str) -> Optional[np.ndarray]:
    """Each run's final evaluation (`eval.json`, written at the end of its schedule: 100 episodes
    with the ant preset, whose metrics.csv has no evaluation column when it evaluates only in-band)
    where every run has one from its last logged iteration; else None."""
    out = []
    for d in dirs:
        row = _last_row(d)
        try:
            with open(os.path.join(d, "eval.json")) as f:
                ev = json.load(f)
        except (OSError, ValueError):
            return None
        if row is None or column not in ev or int(ev.get("iteration", -1)) != int(row["iteration"]):
            return None
        out.append(float(ev[column]))
    return np.array(out) if out else None


def final_success(dirs) -> Optional[np.ndarray]:
    """Each run's success at the end: its final evaluation (`eval.json`, see `final_evals`),
    else the last periodic evaluation in metrics.csv; None where neither exists."""
    v = final_evals(dirs, "eval/success_rate")
    if v is None:
        cs = curves(dirs, "eval/success_rate", inband=False)
        v = finals(cs) if cs else None
    return v


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _write_csv(path: str, header, rows) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


class Data:
    """What the runs hold, per experiment: seed dirs, finished or not."""

    def __init__(self, args, figs: dict):
        self.args = args
        self.figs = figs
        self.info = {}
        for exp in dict.fromkeys(e for es in figs.values() for e in es):
            gdir = group_dir(exp, args)
            want = {f"s{s}" for s in parse_seeds(exp.seeds)}
            seeds = [d for d in seed_dirs(gdir) if os.path.basename(d) in want]
            if exp.beyond and seeds and _mismatch_or_error(gdir, exp, args):
                seeds = []   # not made with the settings beyond the paper: not drawn as such
            self.info[exp] = dict(dir=gdir, name=shown_name(exp, gdir), seeds=seeds,
                                  finished=bool(seeds or not exp.beyond) and group_state(
                                      gdir, schedule(exp, args)) == "finished")

    def dirs(self, exp):
        return self.info[exp]["seeds"] if exp in self.info else []

    def finished(self, exp):
        return exp in self.info and self.info[exp]["finished"]


def curve_figure(data: Data, panels: list, column: str, ylabel: str, path: str, csv_path: str,
                 log: bool = False, hline: Optional[tuple] = None,
                 arm: Optional[tuple] = None) -> Optional[str]:
    """panels: [(title, [Exp, ...])]; one line per Exp (mean +- s.e. over its seeds). `arm`:
    (CSV column, {Exp: (value, legend label)}) for lines of one algorithm that differ otherwise."""
    plt = _plt()
    rows, drawn = [], 0
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.2), squeeze=False)
    for ax, (title, exps) in zip(axes[0], panels):
        for exp in exps:
            cs = curves(data.dirs(exp), column)
            if not cs:
                continue
            grid, mean, se, n = mean_se(cs)
            env = exp.run_env(data.args.env_map)
            extra = [arm[1][exp][0]] if arm else []
            for g, m, s in zip(grid, mean, se):
                rows.append([title, env, exp.algo] + extra + [exp.subgoal, int(g), m, s, n,
                                                               int(data.finished(exp))])
            label = arm[1][exp][1] if arm else NAMES[exp.algo]
            color = None if arm else COLORS.get(exp.algo)
            line, = ax.plot(grid, mean, label=f"{label} (n={n})", color=color)
            if n > 1:
                ax.fill_between(grid, mean - se, mean + se, color=line.get_color(), alpha=0.25)
            drawn += 1
        if hline is not None and hline[0] == title:
            ax.axhline(hline[1], ls="--", color="k", label=hline[2])
        ax.set_title(title)
        ax.set_xlabel("episodes")
        ax.set_ylabel(ylabel)
        positive = [y[y > 0] for y in (np.asarray(l.get_ydata(), float) for l in ax.get_lines())]
        positive = np.concatenate(positive) if positive else np.zeros(0)
        if log and positive.size:   # zeros (an option never executed) fall below the axis
            ax.set_yscale("log")
            ax.set_ylim(bottom=positive.min() / 3, top=max(1.0, positive.max() * 1.5))
        if column.endswith("success_rate"):
            ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    if not drawn:
        plt.close(fig)
        return None
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    _write_csv(csv_path, ["panel", "env", "algo"] + ([arm[0]] if arm else [])
               + ["subgoal", "episodes", "mean", "se", "n_seeds", "finished"], rows)
    return path


MAZE_TITLES = {"u_maze": "U-maze", "medium": "large maze (medium)", "four_rooms": "four rooms",
               "large": "D4RL large maze (beyond the paper)", "ant_reacher": "Ant-Reacher"}


def _maze_title(maze: str, env_map: dict) -> str:
    run = env_map.get(maze, maze)
    title = MAZE_TITLES.get(maze, maze)
    return title if run == maze else f"{title} (as {run})"


BEYOND_TITLE = "{}: DSC++ beyond the paper"


def fig6(data: Data, out: str) -> Optional[str]:
    """Figure 6: one panel per maze at the paper's rule, then one per maze where groups of DSC++
    with the preset's settings beyond the paper exist (titled so)."""
    exps = [e for e in data.figs["6"] if e.tag != "long" and not e.beyond]
    mazes = list(dict.fromkeys(e.env for e in exps))
    panels = [(_maze_title(m, data.args.env_map), [e for e in exps if e.env == m]) for m in mazes]
    beyond = [e for e in data.figs["6"] if e.beyond and data.dirs(e)]   # drawn where they exist
    panels += [(BEYOND_TITLE.format(_maze_title(m, data.args.env_map)),
                [e for e in beyond if e.env == m])
               for m in dict.fromkeys(e.env for e in beyond)]
    hline = None
    long = [e for e in data.figs["6"] if e.tag == "long"]
    v = final_success(data.dirs(long[0])) if long else None
    if v is not None:
        hline = (_maze_title("u_maze", data.args.env_map), float(v.mean()),
                 f"TD3+HER after {long[0].episodes} episodes (n={len(v)})")
    path = curve_figure(data, panels, "eval/success_rate", "success rate from the start",
                        os.path.join(out, "fig6.png"), os.path.join(out, "fig6.csv"), hline=hline)
    if path and hline is not None:
        with open(os.path.join(out, "fig6.csv"), "a", newline="") as f:
            csv.writer(f).writerow([hline[0], long[0].run_env(data.args.env_map), "td3_her_long",
                                    "robust", long[0].episodes, hline[1], "", "", ""])
    return path


def fig5(data: Data, out: str) -> Optional[str]:
    return curve_figure(data, [(_maze_title("u_maze", data.args.env_map), data.figs["5"])],
                        "options/chain_probability", "chain probability (eq. 3)",
                        os.path.join(out, "fig5.png"), os.path.join(out, "fig5.csv"), log=True)


def _a2_arms(exps: list) -> dict:
    """{Exp: (critic column value, legend label)} for appendix Figure 2's two arms."""
    return {e: (("per_option", f"{NAMES[e.algo]}, one critic per option")
                if e.tag.endswith("optcritic")
                else ("shared", f"{NAMES[e.algo]}, one shared critic")) for e in exps}


def figA2(data: Data, out: str) -> Optional[str]:
    exps = data.figs.get("A2", [])
    return curve_figure(data, [(_maze_title("u_maze", data.args.env_map), exps)],
                        "eval/success_rate", "success rate from the start",
                        os.path.join(out, "figA2.png"), os.path.join(out, "figA2.csv"),
                        arm=("critic", _a2_arms(exps)))


def figA3(data: Data, out: str) -> Optional[str]:
    return curve_figure(data, [(_maze_title("u_maze", data.args.env_map), data.figs["A3"])],
                        "options/num_options", "number of options (incl. global)",
                        os.path.join(out, "figA3.png"), os.path.join(out, "figA3.csv"))


# ------------------------------------------------------------------------------------------------
# Figure 4 and appendix Figure 1: states from checkpoints (JAX from here on)
# ------------------------------------------------------------------------------------------------
def _cached(path: str, step: Optional[int]):
    """The cached evaluation at `path` if it was made at checkpoint `step` (None: any step, for
    lean copies of runs whose checkpoints are gone)."""
    if os.path.isfile(path):
        z = np.load(path)
        if step is None or int(z["step"]) == step:
            return {k: z[k] for k in z.files}
    return None


def cached_a1_steps(seed_dir: str) -> list:
    """The checkpoints that appendix Figure 1's evaluations were cached at in SEED_DIR."""
    try:
        names = os.listdir(seed_dir)
    except OSError:
        return []
    pre, suf = "reproduce_a1_", ".npz"
    return sorted(int(n[len(pre):-len(suf)]) for n in names
                  if n.startswith(pre) and n.endswith(suf) and n[len(pre):-len(suf)].isdigit())


def corner_eval(seed_dir: str, step: Optional[int]) -> Optional[dict]:
    """Episodes from the four corners with the evaluation policy (as `eval --starts`), cached
    in SEED_DIR/reproduce_fig4.npz for the checkpoint `step`. `step` None (no checkpoint left):
    the cached result, whichever checkpoint it came from, or None."""
    path = os.path.join(seed_dir, "reproduce_fig4.npz")
    got = _cached(path, step)
    if got is not None or step is None:
        return got

    cfg, state = load_run(seed_dir, step)
    _, res = evaluate(state, jax.random.PRNGKey(0), starts=np.asarray(CORNERS))
    steps = np.asarray(res.steps)
    success = np.asarray(res.success).astype(int)
    out = dict(step=np.asarray(step), episodes=np.asarray(int(state.counters.episodes)),
               steps=steps, success=success,
               # sparse reward: -1 a step, 0 on the step that reaches the goal
               ret=-(steps - success).astype(float),
               xy=np.asarray(res.xy), option=np.asarray(res.option),
               max_options=np.asarray(cfg.chain.max_options))
    np.savez(path, **out)
    return out


def fig4(data: Data, out: str) -> Optional[str]:
    from matplotlib.collections import LineCollection

    exps = data.figs["4"]
    results, rows = {}, []
    for exp in exps:
        per_seed = []
        for d in data.dirs(exp):
            steps = checkpoint_steps(data.info[exp]["dir"])
            r = corner_eval(d, steps[-1] if steps else None)
            if r is None:
                continue
            per_seed.append((d, r))
            for (sx, sy), st, su, rt in zip(CORNERS, r["steps"], r["success"], r["ret"]):
                rows.append([exp.subgoal, exp.run_env(data.args.env_map), exp.algo,
                             os.path.basename(d), int(r["step"]), int(r["episodes"]), sx, sy,
                             int(su), int(st), float(rt), int(data.finished(exp))])
        if per_seed:
            results[exp] = per_seed
    if not results:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for ax, exp in zip(axes[:2], exps):
        ax.set_title(f"{NAMES[exp.algo]}, {exp.subgoal} subgoals")
        if exp not in results:
            ax.text(0.5, 0.5, "not run", ha="center", transform=ax.transAxes)
            continue
        d, r = results[exp][0]
        cfg = load_config(d)
        draw_maze(ax, maze_layout(cfg))
        cmap = plt.get_cmap("tab10" if int(r["max_options"]) <= 10 else "tab20")
        for e in range(r["xy"].shape[1]):
            L = int(r["steps"][e])
            seg = np.stack([r["xy"][:L, e], r["xy"][1:L + 1, e]], 1)
            opt = r["option"][:L, e]
            ax.add_collection(LineCollection(seg, colors=[cmap(int(o) % cmap.N) if o >= 0 else
                                                          "0.5" for o in opt], linewidths=1.8,
                                             zorder=3))
            ax.plot(*r["xy"][0, e], "s", color="k", ms=4, zorder=4)
        ax.set_xlabel(f"x   ({os.path.basename(d)}, {int(r['episodes'])} episodes; colour: option)")
    ax = axes[2]
    labels, means, ses = [], [], []
    for exp in exps:
        if exp not in results:
            continue
        per = np.array([r["ret"].mean() for _, r in results[exp]])
        labels.append(f"{exp.subgoal}\n(n={len(per)})")
        means.append(per.mean())
        ses.append(per.std(ddof=1) / np.sqrt(len(per)) if len(per) > 1 else 0.0)
    ax.bar(labels, means, yerr=ses, capsize=6, color=["tab:blue", "tab:orange"][:len(labels)])
    ax.set_ylabel("average reward from the four corners")
    ax.set_title("higher is better (mean ± s.e. over seeds)")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    path = os.path.join(out, "fig4.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    _write_csv(os.path.join(out, "fig4.csv"),
               ["subgoal", "env", "algo", "seed_dir", "checkpoint", "episodes_trained", "start_x",
                "start_y", "success", "steps", "return", "finished"], rows)
    return path


def goal_regions(seed_dir: str, step: int, resolution: int, recompute: bool = True) -> dict:
    """The goal option's optimistic and pessimistic decision values on a grid over the arena at
    checkpoint `step`, cached in SEED_DIR/reproduce_a1_<step>.npz (made again at another
    `resolution` unless `recompute` is off: a lean copy without checkpoints)."""
    path = os.path.join(seed_dir, f"reproduce_a1_{step}.npz")
    got = _cached(path, step)
    if got is not None and (got["opt"].shape[0] == resolution or not recompute):
        return got

    cfg, state = load_run(seed_dir, step)
    xmin, xmax, ymin, ymax = maze_layout(cfg).bounds
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, resolution), np.linspace(ymin, ymax, resolution))
    grid = jnp.asarray(np.stack([gx.ravel(), gy.ravel()], -1), jnp.float32)
    clf = jax.tree_util.tree_map(lambda a: a[1], state.chain.clf)   # row 1: the goal option
    dec = jax.jit(svm.decision_function)
    opt = np.asarray(dec(clf.optimistic, grid)).reshape(gx.shape)
    pes = np.asarray(dec(clf.pessimistic, grid)).reshape(gx.shape)
    if not bool(clf.optimistic_fitted):
        opt = np.full(gx.shape, -1.0)
    if not bool(clf.pessimistic_fitted):
        pes = np.full(gx.shape, -1.0)
    out = dict(step=np.asarray(step), episodes=np.asarray(int(state.counters.episodes)),
               gx=gx, gy=gy, opt=opt, pes=pes)
    np.savez(path, **out)
    return out


def _pick(steps: list, k: int) -> list:
    if len(steps) <= k:
        return steps
    return [steps[i] for i in sorted(set(np.linspace(0, len(steps) - 1, k).round().astype(int)))]


def _from_first_fitted(seed_dir: str, steps: list, resolution: int, recompute: bool) -> list:
    """`steps` from the first checkpoint where the goal option holds a region: the warm-up's
    checkpoints (no region at all) show nothing worth a panel. All of `steps` if none has one."""
    for i, step in enumerate(steps):
        r = goal_regions(seed_dir, step, resolution, recompute=recompute)
        if (r["opt"] > 0).any() or (r["pes"] > 0).any():
            return steps[i:]
    return steps


def figA1(data: Data, out: str) -> Optional[str]:
    k = data.args.a1_panels
    todo = []   # (exp, seed dir, checkpoints kept, checkpoints shown)
    for e in data.figs["A1"]:
        if data.dirs(e):
            d = data.dirs(e)[0]
            kept = checkpoint_steps(data.info[e]["dir"])
            steps = _pick(_from_first_fitted(d, kept or cached_a1_steps(d),
                                             data.args.a1_resolution, bool(kept)), k)
            if steps:
                todo.append((e, d, kept, steps))
    if not todo:
        return None
    plt = _plt()
    fig, axes = plt.subplots(len(todo), k, figsize=(3.6 * k, 3.6 * len(todo)), squeeze=False)
    rows = []
    for i, (exp, d, kept, steps) in enumerate(todo):
        cfg = load_config(d)
        layout = maze_layout(cfg)
        for ax in axes[i]:
            ax.axis("off")
        for j, step in enumerate(steps):
            r = goal_regions(d, step, data.args.a1_resolution, recompute=bool(kept))
            cell = (r["gx"][0, 1] - r["gx"][0, 0]) * (r["gy"][1, 0] - r["gy"][0, 0])
            a_opt, a_pes = float((r["opt"] > 0).sum() * cell), float((r["pes"] > 0).sum() * cell)
            rows.append([exp.algo, exp.run_env(data.args.env_map), os.path.basename(d), step,
                         int(r["episodes"]), a_opt, a_pes, int(data.finished(exp))])
            ax = axes[i, j]
            ax.axis("on")
            draw_maze(ax, layout)
            if (r["opt"] > 0).any():
                ax.contourf(r["gx"], r["gy"], (r["opt"] > 0).astype(float), levels=[0.5, 1.5],
                            colors=["darkred"], alpha=0.5, zorder=2)
            if (r["pes"] > 0).any() and (r["pes"] < 0).any():
                ax.contour(r["gx"], r["gy"], r["pes"], levels=[0.0], colors="k", linewidths=1.5,
                           zorder=4)
            ax.set_title(f"{NAMES[exp.algo]}: iteration {step}, {int(r['episodes'])} episodes",
                         fontsize=9)
    fig.suptitle("goal option: optimistic region (red), pessimistic contour (black)"
                 + (" (DSC: one classifier)" if any(t[0].algo == "dsc" for t in todo) else ""),
                 fontsize=10)
    fig.tight_layout()
    path = os.path.join(out, "figA1.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    _write_csv(os.path.join(out, "figA1.csv"),
               ["algo", "env", "seed_dir", "checkpoint", "episodes", "optimistic_area",
                "pessimistic_area", "finished"], rows)
    return path


# ------------------------------------------------------------------------------------------------
# Claims
# ------------------------------------------------------------------------------------------------
def a1_verdict(areas: dict, ours: str) -> tuple:
    """Appendix Figure 1's claim from the goal option's region areas, {algo: [(episodes,
    optimistic area, pessimistic area), ...]}: (text, holds). Each algorithm's areas count from
    its first checkpoint where the goal option had been fitted (those of the warm-up have no
    region at all). Holds when DSC's region ends smaller than the pessimistic region of `ours`,
    whose optimistic region does not grow and whose pessimistic region does not shrink."""
    txt, first = [], {}
    for a, v in areas.items():
        v = sorted(v)
        first[a] = next((x for x in v if x[1] > 0 or x[2] > 0), v[0])
        txt.append(f"{NAMES[a]}: optimistic {first[a][1]:.3g} -> {v[-1][1]:.3g}, pessimistic "
                   f"{first[a][2]:.3g} -> {v[-1][2]:.3g} (episodes {first[a][0]} -> {v[-1][0]})")
    ok = False
    if "dsc" in areas and ours in areas and ours != "dsc":
        d, o, f = max(areas["dsc"]), max(areas[ours]), first[ours]
        ok = d[2] < o[2] and o[1] <= f[1] and o[2] >= f[2]
    return "; ".join(txt), ok


def _fmt(x: np.ndarray) -> str:
    if x.size == 0:
        return "-"
    if x.size == 1:
        return f"{x.mean():.3g}"
    return f"{x.mean():.3g} ± {_se(x):.2g}"


def _se(x: np.ndarray) -> float:
    """Standard error of the mean over seeds (0 for one seed)."""
    return float(x.std(ddof=1) / np.sqrt(x.size)) if x.size > 1 else 0.0


def above(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the per-seed values `a` end above `b` by more than one standard error of the
    difference of their means: with 5 seeds a mean that is ahead by less than that is not an
    ordering (0.16 ± 0.16 against 0.14 ± 0.14 is a tie)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return bool(a.mean() - b.mean() > np.hypot(_se(a), _se(b)))


def _status(ok: bool, complete) -> str:
    if not complete:
        return "incomplete (runs missing or not finished)"
    return "reproduced" if ok else "not reproduced"


def claims(data: Data, args, figures: dict) -> list:
    """[(figure, claim, measured, status)] for every claim of the paper."""
    fig6_exps = [e for e in data.figs.get("6", []) if e.tag != "long" and not e.beyond]

    def final(exp, col="eval/success_rate", reduce="last"):
        if reduce == "last" and col.startswith("eval/"):
            v = final_evals(data.dirs(exp), col)
            if v is not None:
                return v
        cs = curves(data.dirs(exp), col, inband=reduce != "last")
        if not cs:
            return None
        return finals(cs) if reduce == "last" else np.array([c[1].max() for c in cs])

    def where(exp):
        return f"{exp.run_env(args.env_map)}, {len(data.dirs(exp))} seeds"

    out = []
    # --- Figure 6 --------------------------------------------------------------------------
    # the paper's claims are about its three mazes (D4RL's large maze is drawn, not claimed)
    mazes = [m for m in dict.fromkeys(e.env for e in fig6_exps) if m in MAZES]
    for maze in mazes or MAZES:
        exps = {e.algo: e for e in fig6_exps if e.env == maze}
        got = {a: final(e) for a, e in exps.items()}
        got = {a: v for a, v in got.items() if v is not None}
        claim = f"{maze}: MB-DSC++ and MF-DSC++ outperform every baseline (final success)"
        if "6" not in data.figs or not got:
            out.append(("6", claim, "-", "not run"))
            continue
        ours = [a for a in ("mb_dscpp", "mf_dscpp") if a in got]
        base = [a for a in ("td3_her", "mb_flat", "mb_flat_value", "dsc") if a in got]
        measured = "; ".join(f"{NAMES[a]} {_fmt(v)}" for a, v in got.items()) + \
            f" ({exps[next(iter(got))].run_env(args.env_map)}, success at the end)"
        complete = set(got) >= set(FIG6_ALGOS) and all(data.finished(e) for e in exps.values())
        ok = bool(ours) and all(above(got[o], got[b]) for o in ours for b in base)
        out.append(("6", claim, measured, _status(ok, complete)))
    for maze in mazes or MAZES:
        exps = {e.algo: e for e in fig6_exps if e.env == maze and e.algo in ("mb_flat",
                                                                               "mb_flat_value")}
        got = {a: final(e, reduce="max") for a, e in exps.items()}
        got = {a: v for a, v in got.items() if v is not None}
        claim = f"{maze}: both flat model-based baselines never exceed 0 % success"
        if not got:
            out.append(("6", claim, "-", "not run"))
            continue
        measured = "; ".join(f"{NAMES[a]} best eval {_fmt(v)} ({where(exps[a])})"
                             for a, v in got.items())
        ok = all((v == 0).all() for v in got.values())
        out.append(("6", claim, measured, _status(ok, len(got) == 2 and all(
            data.finished(e) for e in exps.values()))))
    for algo in ("dsc", "td3_her"):
        exps = {e.env: e for e in fig6_exps if e.algo == algo and e.env in MAZES}
        got = {m: final(e, reduce="max") for m, e in exps.items()}
        got = {m: v for m, v in got.items() if v is not None}
        claim = (f"{NAMES[algo]} reaches > 0 % success on U-maze only" if algo == "dsc" else
                 "TD3+HER stays at 0 % on the large maze and four rooms (it rose above 0 only on "
                 "U-maze, after 12,000 episodes)")
        if not got:
            out.append(("6", claim, "-", "not run"))
            continue
        measured = "; ".join(f"{m}: best eval {_fmt(v)} ({where(exps[m])})" for m, v in got.items())
        ok = all(((v > 0).any() if m == "u_maze" else (v == 0).all()) for m, v in got.items())
        if algo == "td3_her":   # the paper: TD3 needs far more episodes to get above 0 on U-maze
            ok = all((v == 0).all() for m, v in got.items() if m != "u_maze")
        complete = set(got) >= set(MAZES) and all(data.finished(e) for e in exps.values())
        out.append(("6", claim, measured, _status(ok, complete)))
    # DSC++ with the preset's settings beyond the paper: shown beside the paper's panels, not
    # one of its claims
    beyond = [e for e in data.figs.get("6", []) if e.beyond]
    for maze in dict.fromkeys(e.env for e in beyond):
        exps = {e.algo: e for e in beyond if e.env == maze}
        got = {a: final(e) for a, e in exps.items()}
        got = {a: v for a, v in got.items() if v is not None}
        claim = (f"{maze}, beyond the paper (not a claim of the paper): DSC++ with the preset's "
                 f"settings beyond the paper ({beyond_words(maze, args)})")
        measured = ("; ".join(f"{NAMES[a]} {_fmt(v)}" for a, v in got.items())
                    + f" ({where(exps[next(iter(got))])}, success at the end)") if got else "-"
        done = bool(got) and all(data.finished(e) for e in exps.values())
        out.append(("6", claim, measured, "beyond the paper" if done else
                    "not run" if not got else "incomplete (runs missing or not finished)"))
    long = [e for e in data.figs.get("6", []) if e.tag == "long"]
    claim = "TD3+HER after 12,000 episodes on U-maze: success > 0 (dashed line)"
    v = final(long[0]) if long else None
    if v is None:
        out.append(("6", claim, "-", "not run (train it with --long-td3)"))
    else:
        out.append(("6", claim, f"{_fmt(v)} ({where(long[0])}, {long[0].episodes} episodes)",
                    _status(bool(v.mean() > 0), data.finished(long[0]))))
    # --- Figure 5 --------------------------------------------------------------------------
    exps = {e.algo: e for e in data.figs.get("5", [])}
    got = {a: final(e, "options/chain_probability") for a, e in exps.items()}
    got = {a: v for a, v in got.items() if v is not None}
    claim = ("U-maze: chain probability (eq. 3) rises with each proposal: "
             "DSC < + dual classifiers < MF-DSC++ < MB-DSC++")
    if not got:
        out.append(("5", claim, "-", "not run"))
    else:
        order = [a for a in FIG5_ALGOS if a in got]
        measured = "; ".join(f"{NAMES[a]} {_fmt(got[a])}" for a in order) + \
            f" ({exps[order[0]].run_env(args.env_map)}, at the end)"
        ok = all(above(got[b], got[a]) for a, b in zip(order, order[1:]))
        complete = len(order) == 4 and all(data.finished(e) for e in exps.values())
        out.append(("5", claim, measured, _status(ok, complete)))
    # --- Figure 4 --------------------------------------------------------------------------
    claim = ("Ant-Reacher, after 1,000 episodes: DP subgoals collect a higher average reward "
             "from the four corners than robust subgoals")
    path = os.path.join(args.out, "fig4.csv")
    rets = {}
    if figures.get("4") and os.path.isfile(path):
        with open(path) as f:
            for r in csv.DictReader(f):
                rets.setdefault(r["subgoal"], {}).setdefault(r["seed_dir"], []).append(
                    float(r["return"]))
    if not rets:
        out.append(("4", claim, "-", "not run"))
    else:
        per = {s: np.array([np.mean(v) for v in d.values()]) for s, d in rets.items()}
        e4 = data.figs["4"]
        measured = "; ".join(f"{s}: {_fmt(v)}" for s, v in per.items()) + \
            f" ({e4[0].run_env(args.env_map)}, {NAMES[e4[0].algo]}, {e4[0].episodes} episodes)"
        ok = "dp" in per and "robust" in per and above(per["dp"], per["robust"])
        out.append(("4", claim, measured, _status(ok, len(per) == 2 and all(
            data.finished(e) for e in e4))))
    # --- Appendix Figure 1 -----------------------------------------------------------------
    claim = ("Ant-Reacher goal option: DSC's initiation region ends smaller than DSC++'s; DSC++'s "
             "optimistic region shrinks while its pessimistic region grows")
    path = os.path.join(args.out, "figA1.csv")
    areas = {}
    if figures.get("A1") and os.path.isfile(path):
        with open(path) as f:
            for r in csv.DictReader(f):
                areas.setdefault(r["algo"], []).append((int(r["episodes"]),
                                                        float(r["optimistic_area"]),
                                                        float(r["pessimistic_area"])))
    if not areas:
        out.append(("A1", claim, "-", "not run"))
    else:
        ea = data.figs["A1"]
        text, ok = a1_verdict(areas, ea[-1].algo)
        measured = text + f" (area, {ea[0].run_env(args.env_map)}, one seed)"
        out.append(("A1", claim, measured, _status(ok, len(areas) == 2 and all(
            data.finished(e) for e in ea))))
    # --- Appendix Figure 2 -----------------------------------------------------------------
    arms = {("per_option" if e.tag.endswith("optcritic") else "shared"): e
            for e in data.figs.get("A2", [])}
    got = {k: final(e) for k, e in arms.items()}
    got = {k: v for k, v in got.items() if v is not None}
    claim = ("MF-DSC++ on U-maze learns better with one shared critic than with one critic per "
             "option")
    if not got:
        out.append(("A2", claim, "-", "not run"))
    else:
        words = {"shared": "one shared critic", "per_option": "one critic per option"}
        measured = "; ".join(f"{words[k]} {_fmt(got[k])}" for k in ("shared", "per_option")
                             if k in got) + \
            f" ({next(iter(arms.values())).run_env(args.env_map)}, success at the end)"
        ok = len(got) == 2 and above(got["shared"], got["per_option"])
        complete = len(got) == 2 and all(data.finished(e) for e in arms.values())
        out.append(("A2", claim, measured, _status(ok, complete)))
    # --- Appendix Figure 3 -----------------------------------------------------------------
    exps = {e.algo: e for e in data.figs.get("A3", [])}
    got = {a: final(e, "options/num_options") for a, e in exps.items()}
    got = {a: v for a, v in got.items() if v is not None}
    claim = "U-maze: baseline DSC needs more options than the DSC++ variants"
    if not got:
        out.append(("A3", claim, "-", "not run"))
    else:
        measured = "; ".join(f"{NAMES[a]} {_fmt(v)}" for a, v in got.items()) + \
            f" ({next(iter(exps.values())).run_env(args.env_map)}, options at the end, incl. " \
            "global)"
        ours = [a for a in ("mf_dscpp", "mb_dscpp") if a in got]
        ok = "dsc" in got and bool(ours) and all(above(got["dsc"], got[a]) for a in ours)
        complete = "dsc" in got and len(ours) == 2 and all(data.finished(e) for e in exps.values())
        out.append(("A3", claim, measured, _status(ok, complete)))
    return out


def _shown_path(path: str) -> str:
    rel = os.path.relpath(path, ROOT)
    return path if rel.startswith("..") else rel


NOTES_HEADING = "\n## Notes\n"


def failure_lines(data: Data) -> list:
    """One line per group with a skill chain: how many of its seeds got each
    `dscpp_jax.diagnose` verdict (solved, falls, weak link, broke late, ..., and unfinished for
    seeds without their final evaluation yet)."""
    out = []
    for info in data.info.values():
        rows = []
        for d in info["seeds"]:
            try:
                rows.append(diagnose.diagnose_run(d))
            except ValueError:   # no metrics yet, or no skill chain (flat learners)
                continue
        if rows:
            out.append(f"- {info['name']}: {diagnose.format_summary(rows)}")
    return out


def group_wall(data: Data, exp) -> Optional[float]:
    """A group's training wall-clock in seconds (its seeds share one program: the largest
    `wall_clock` of their last rows, which counts every resumed call); None without rows."""
    walls = [r["wall_clock"] for r in map(_last_row, data.dirs(exp)) if r is not None]
    return float(max(walls)) if walls else None


def training_time_lines(data: Data) -> list:
    """A table of the training wall-clock per figure (the sum over the groups it draws) and the
    total over every group once; groups trained beside others on one device count their own
    elapsed time."""
    walls = {exp: group_wall(data, exp) for exp in data.info}
    out = ["| figure | groups with runs | training wall-clock (h) |", "|---|---:|---:|"]
    for fig in FIGS:
        exps = [e for e in dict.fromkeys(data.figs.get(fig, ())) if walls.get(e) is not None]
        if exps:
            total = sum(walls[e] for e in exps)
            out.append(f"| {fig} | {len(exps)} | {total / 3600:.2f} |")
    have = [w for w in walls.values() if w is not None]
    if not have:
        return []
    out.append(f"| all (each group once) | {len(have)} | {sum(have) / 3600:.2f} |")
    return out


# what each figure of the paper shows, for the README's figure list
FIG_CAPTIONS = {
    "6": "success rate from the task start against episodes, every learner on each maze at "
         "the paper's rule, then DSC++ with the preset's settings beyond the paper",
    "5": "chain probability (eq. 3) on U-maze",
    "4": "Ant-Reacher: episodes from the four corners with robust and DP subgoals, and their "
         "average reward",
    "A1": "the goal option's optimistic and pessimistic initiation regions over training",
    "A2": "MF-DSC++ on U-maze with one shared critic and with one critic per option",
    "A3": "number of options on U-maze",
}


def write_readme(data: Data, args, figures: dict, status: dict) -> str:
    """README.md in --out: the command, the claims table, the figures, the protocol and how each
    group's seeds end; a hand-written section that starts with the heading "## Notes" below them
    survives a re-run."""
    path = os.path.join(args.out, "README.md")
    cmd = "python experiments/reproduce.py " + " ".join(args.argv)
    anything = any(data.dirs(e) for e in data.info)
    title = "# The paper's figures, reproduced"
    if args.env_map:   # e.g. the point-mass twins: say so before anything else
        title += (" on other environments ("
                  + ", ".join(f"{k} -> {v}" for k, v in args.env_map.items()) + ")")
    lines = [
        title,
        "",
        "Each claim of the paper (Figures 4-6, appendix Figures 1-3) checked against seed groups "
        "trained by `experiments/reproduce.py` under "
        f"`{_shown_path(args.runs_root)}`; "
        + ("every number comes from their `metrics.csv`, `eval.json` and checkpoints (or "
           "figure evaluations cached beside them). "
           + ("Drawn from the runs as they are with (without `--report-only` it trains what is "
              "unfinished):" if args.report_only else
              "Made with (re-run it to continue unfinished runs and refresh this page):")
           if anything else
           "**no run exists there yet, so every claim below is *not run*.** This page was "
           "made with:"),
        "",
        f"    {cmd.strip()}",
        "",
        "To train and draw them yourself (on a GPU host; re-run the same command to continue "
        "where it stopped): `make reproduce FIG=all ARGS='--time-budget 3600 --long-td3'`, or "
        "one figure at a time, e.g. `make reproduce FIG=6`.",
        "",
        "## Claims",
        "",
        "A claim is *reproduced* when the measured means order as the paper says, each step "
        "by more than one standard error of the difference (criteria in "
        "`experiments/reproduce.py`, `claims`); *incomplete* while some of its runs have not "
        "reached their schedule; *not run* when no run holds data for it.",
        "",
        "| figure | paper's claim | measured | status |",
        "|---|---|---|---|",
    ]
    for fig, claim, measured, st in claims(data, args, figures):
        lines.append(f"| {fig} | {claim} | {measured} | {st} |")
    lines += ["", "## Figures"]
    for fig in FIGS:
        p = figures.get(fig)
        if p:
            name = os.path.basename(p)
            csvp = os.path.splitext(name)[0] + ".csv"
            lines += ["", f"Figure {fig}: {FIG_CAPTIONS[fig]} (numbers: [`{csvp}`]({csvp}))",
                      "", f"![Figure {fig}]({name})"]
        else:
            lines += ["", f"Figure {fig}: not drawn (no runs yet)"]
    lines += [
        "",
        "## Protocol",
        "",
        f"Preset `{args.preset}`, seeds {args.seeds}, {args.episodes} episodes "
        f"(Figure 4 / appendix Figure 1: {args.fig4_episodes} on Ant-Reacher), success from the "
        "task start, mean ± standard error over seeds; every group with "
        + ", ".join(f"`{x}`" for x in PAPER_SETS)
        + "".join(f" (`{', '.join(v)}` on {k})" for k, v in PAPER_ENV_SETS.items())
        + (f"; overrides: {', '.join(args.set)}" if args.set else "")
        + (f"; envs replaced: {', '.join(f'{k} -> {v}' for k, v in args.env_map.items())}"
           if args.env_map else "") + "." + _frontier_note(data, args),
    ]
    why = failure_lines(data)
    if why:
        lines += ["", "How each group's seeds end (`python -m dscpp_jax.cli diagnose GROUP_DIR` "
                  "gives the row per seed; the verdicts are explained in `docs/cli.md`, diagnose):", ""]
        lines += why
    times = training_time_lines(data)
    if times:
        lines += ["", "Training time, from each group's `metrics.csv` (`wall_clock` at its last "
                  "row; the device of each run is in its `group.json`):", ""]
        lines += times
    other = mismatch_lines(data, args)
    if other:
        lines += ["", "Groups made with other settings than this version's preset and this "
                  "call's sets (the figures and claims above show them as made; to train one "
                  "with the current settings, move its directory away and run the command "
                  "without `--report-only`):", ""]
        lines += other
    if status:
        lines += ["", "Runs (this call):", ""]
        lines += [f"- `{k}`: {v}" for k, v in status.items()]
    text = "\n".join(lines) + "\n"
    try:   # a "## Notes" section written by hand below the generated part is kept
        with open(path) as f:
            old = f.read()
        i = old.find(NOTES_HEADING)
        if i >= 0:
            text += "\n" + old[i:]
    except OSError:
        pass
    with open(path, "w") as f:
        f.write(text)
    return path


# ------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fig", default="all", help="4, 5, 6, A1, A2, A3 or all (comma separated)")
    p.add_argument("--seeds", default="0-4", help="seeds of every group (default 0-4: 5 seeds)")
    p.add_argument("--episodes", "--total-episodes", dest="episodes", type=int, default=2001,
                   help="episodes per run of Figures 5, 6, A2 and A3 (default 2001)")
    p.add_argument("--total-steps", dest="total_steps", type=int, default=None,
                   help="also stop each run at this many env steps (default: loose enough that "
                        "the episode budget binds)")
    p.add_argument("--preset", default="fast", choices=("fast", "paper"))
    p.add_argument("--algos", default=None,
                   help="only these algorithms (comma separated; default: all the figures name)")
    p.add_argument("--mazes", default=None,
                   help="Figure 6's mazes (default u_maze,medium,four_rooms)")
    p.add_argument("--env-map", dest="env_map_list", action="append", default=[],
                   metavar="PAPER=ENV", help="train ENV where the paper uses PAPER, e.g. "
                   "u_maze=point_u_maze (repeatable)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="Config override for every run (repeatable)")
    p.add_argument("--long-td3", action="store_true",
                   help="also train TD3+HER on U-maze for --long-td3-episodes (Figure 6's "
                        "dashed line)")
    p.add_argument("--long-td3-episodes", type=int, default=12000)
    p.add_argument("--long-td3-seeds", default=None,
                   help="seeds of the 12,000-episode TD3+HER group (default: --seeds); e.g. 0-7 "
                        "to split it evenly over 4 GPUs given to one call (--gpus 0+1+2+3)")
    p.add_argument("--fig4-algo", default="mb_dscpp", help="Figure 4's algorithm (and A1's DSC++)")
    p.add_argument("--fig4-episodes", type=int, default=1000)
    p.add_argument("--a1-seeds", default="0", help="seeds of appendix Figure 1's runs")
    p.add_argument("--a1-keep", type=int, default=1000,
                   help="checkpoints appendix Figure 1's runs keep (default: all)")
    p.add_argument("--a1-every", type=int, default=5,
                   help="iterations between the checkpoints of appendix Figure 1's runs (default "
                        "5: the goal option's regions early in training; the preset's 25 shows "
                        "the first one after about 240 episodes on the ant)")
    p.add_argument("--a1-panels", type=int, default=4, help="checkpoints shown per algorithm")
    p.add_argument("--a1-resolution", type=int, default=80)
    p.add_argument("--runs-root", default=os.path.join("runs", "paper"))
    p.add_argument("--out", default=os.path.join("experiments", "results", "paper"))
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="per train call: checkpoint and stop after this long (run again to go on)")
    p.add_argument("--stop-after", type=float, default=None, metavar="SECONDS",
                   help="for the whole call (a job with a wall-clock limit): no train loop runs "
                        "past this many seconds after the call's start; each train call's final "
                        "evaluation and the figures come after it, so leave a few minutes of "
                        "the job's limit for them")
    p.add_argument("--min-call", type=float, default=300, metavar="SECONDS",
                   help="with --stop-after: start no train call with less time left than this "
                        "(default 300)")
    p.add_argument("--jobs", type=int, default=1,
                   help="train calls at once (default 1); with --gpus they are spread over the "
                        "GPUs, and calls that share a GPU split its memory")
    p.add_argument("--gpus", default=None, metavar="LIST",
                   help="e.g. 0,1,2,3: each train call gets one of these GPUs "
                        "(CUDA_VISIBLE_DEVICES); a group's seeds then share that GPU. 0+1+2+3: "
                        "one call gets the four GPUs and splits its group's seeds over them "
                        "(a multiple of 4 seeds). Where CUDA_VISIBLE_DEVICES is set, name GPUs "
                        "from it")
    p.add_argument("--report-only", action="store_true",
                   help="train nothing: figures, CSVs and README from the runs that exist")
    p.add_argument("--dry-run", action="store_true", help="print the train commands only")
    p.add_argument("--beyond-paper", action="store_true",
                   help="also train Figure 6's DSC++ groups with the preset's settings beyond "
                        "the paper (the chain's frontier, the medium maze's TD3); without it "
                        "they are drawn where they exist")
    p.add_argument("--print-commands", action="store_true",
                   help="print one `python -m dscpp_jax.cli train` command per group of the "
                        "figures that has not reached its schedule (to start or continue it), "
                        "to run side by side on one GPU; trains nothing, draws nothing")
    p.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help="deterministic GPU kernels in train and in the evaluations here (default: "
                        "as train: on, except on MuJoCo Warp physics)")
    p.add_argument("--compile-cache", default=None, metavar="DIR")
    p.add_argument("--export-lean", default=None, metavar="DIR",
                   help="at the end, copy what results keep of every run under --runs-root to "
                        "DIR (per seed metrics.csv, config.json, eval.json and the cached "
                        "figure evaluations; group.json; the train logs), not the checkpoints")
    return p


LEAN_FILES = ("metrics.csv", "options.csv", "config.json", "eval.json", "group.json")


def export_lean(runs_root: str, dest: str) -> int:
    """Copy the lean part of every group under `runs_root` to `dest` (same layout): what a
    results directory commits, and all `--report-only` needs to redraw every figure. Returns the
    number of files copied."""
    n = 0
    for root, dirs, files in os.walk(runs_root):
        dirs[:] = [d for d in dirs if d != "checkpoints" and "xla_cache" not in d]
        rel = os.path.relpath(root, runs_root)
        in_logs = rel.split(os.sep)[0] == "logs"
        for f in files:
            keep = (f in LEAN_FILES or (f.startswith("reproduce_") and f.endswith(".npz"))
                    or (in_logs and f.endswith(".log")))
            if keep:
                os.makedirs(os.path.join(dest, rel), exist_ok=True)
                shutil.copy2(os.path.join(root, f), os.path.join(dest, rel, f))
                n += 1
    return n


# the mazes Figure 6 may name (the paper's three and D4RL's large maze) and every env --env-map
# may name in their place (Ant-Reacher for Figure 4 and A1)
FIG6_MAZES = ("u_maze", "medium", "large", "four_rooms")
PAPER_ENVS = FIG6_MAZES + ("ant_reacher",)


def check_args(args) -> None:
    """Every argument a train call or figure would trip over later, as one clear ValueError now."""
    for flag, text, known in (("--algos", args.algos, FIG6_ALGOS + ("dual",)),
                              ("--mazes", args.mazes, FIG6_MAZES)):
        if text is None:
            continue
        items = _csv_list(text, ())
        bad = [x for x in items if x not in known]
        if bad or not items:
            what = f"unknown {', '.join(map(repr, bad))}" if bad else "names nothing"
            raise ValueError(f"{flag} {text!r}: {what}; choose from {', '.join(known)}")
    if args.fig4_algo not in HIERARCHICAL_ALGOS:
        raise ValueError(f"--fig4-algo {args.fig4_algo!r}: Figure 4 compares subgoals of a skill "
                         f"chain; choose from {', '.join(HIERARCHICAL_ALGOS)}")
    for kv in args.env_map_list:
        k, sep, v = kv.partition("=")
        if not sep or k.strip() not in PAPER_ENVS or v.strip() not in envs.ENV_NAMES:
            raise ValueError(f"--env-map {kv!r}: write PAPER=ENV with PAPER one of "
                             f"{', '.join(PAPER_ENVS)} and ENV one of {', '.join(envs.ENV_NAMES)} "
                             "(e.g. --env-map u_maze=point_u_maze)")
    for flag, v in (("--episodes", args.episodes), ("--fig4-episodes", args.fig4_episodes),
                    ("--long-td3-episodes", args.long_td3_episodes), ("--jobs", args.jobs),
                    ("--a1-panels", args.a1_panels), ("--a1-resolution", args.a1_resolution)):
        if v < 1:
            raise ValueError(f"{flag} {v}: give a whole number >= 1")
    if args.total_steps is not None and args.total_steps < 1:
        raise ValueError(f"--total-steps {args.total_steps}: give a whole number >= 1")
    parse_overrides(args.set)   # unknown fields and values of the wrong type, as `train --set` says


def main(argv: Optional[list] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    try:
        check_args(args)
        args.env_map = dict(kv.split("=", 1) for kv in args.env_map_list)
        figs = plan(args)
        parse_seeds(args.seeds)
        parse_seeds(args.a1_seeds)
        if args.long_td3_seeds is not None:
            parse_seeds(args.long_td3_seeds)
        if args.gpus is not None:
            gpu_slots(_csv_list(args.gpus, ()), args.jobs)
            check_gpus_allowed(_csv_list(args.gpus, ()))
        for flag, v in (("--a1-every", args.a1_every), ("--a1-keep", args.a1_keep)):
            if v < 1:
                raise ValueError(f"{flag} {v}: give a number of iterations >= 1")
        for flag, v in (("--time-budget", args.time_budget), ("--stop-after", args.stop_after)):
            if v is not None and not v > 0:
                raise ValueError(f"{flag} {v:g}: give a number of seconds > 0")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.runs_root and not os.path.isabs(args.runs_root) and args.print_commands:
        args.runs_root = os.path.join(ROOT, args.runs_root)
    if args.print_commands:
        print_commands(args, figs)
        return 0
    if args.gpus is None and not args.report_only:
        # several GPUs: one train call per GPU. A group over all of them would need its seeds to
        # be a multiple of the GPUs (5 seeds over 2 GPUs stop with that error)
        ids = visible_gpus()
        if len(ids) > 1:
            args.gpus, args.jobs = ",".join(ids), max(args.jobs, len(ids))
            say(f"[reproduce] {len(ids)} GPUs: each train call takes one of them "
                  f"(--gpus {args.gpus} --jobs {args.jobs}; pass --gpus to choose)", flush=True)
    if args.runs_root and not os.path.isabs(args.runs_root):
        args.runs_root = os.path.join(ROOT, args.runs_root)
    if not os.path.isabs(args.out):
        args.out = os.path.join(ROOT, args.out)
    args.deadline = None if args.stop_after is None else time.time() + args.stop_after
    if args.gpus is not None and not args.report_only:
        try:
            check_slot_sizes(figs, gpu_slots(_csv_list(args.gpus, ()), args.jobs), args)
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    status = {} if args.report_only else train_all(args, figs)
    if args.dry_run:
        return 0
    # figures: JAX (Figure 4, A1) only now, after every train call has given the devices back
    # and without taking 75 % of every visible GPU up front: the evaluations are small, and train
    # calls of other jobs on the host may be using those GPUs
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    use_xla_flags(deterministic_choice(argparse.Namespace(   # evaluates Figure 4's learner
        env="u_maze", set=args.set, algo=args.fig4_algo, deterministic=args.deterministic)))
    use_compile_cache(args.compile_cache)
    os.makedirs(args.out, exist_ok=True)
    # the report covers every figure whose runs exist, whichever this call trained
    everything = plan(argparse.Namespace(**{**vars(args), "fig": "all", "long_td3": True,
                                            "long_td3_seeds": long_td3_seeds(args)}))
    data = Data(args, everything)
    makers = {"6": fig6, "5": fig5, "A2": figA2, "A3": figA3, "4": fig4, "A1": figA1}
    figures = {}
    for fig in FIGS:
        if fig in makers:
            path = makers[fig](data, args.out)
            figures[fig] = path
            if fig in figs or path:
                say(f"[reproduce] figure {fig}: {path or 'no runs yet'}", flush=True)
    readme = write_readme(data, args, figures, status)
    say(f"[reproduce] {readme}")
    if args.export_lean:
        n = export_lean(args.runs_root, args.export_lean)
        say(f"[reproduce] lean copy of {args.runs_root}: {n} files in {args.export_lean}")
    return 1 if any(str(v).startswith(("failed", "mismatch")) for v in status.values()) else 0


if __name__ == "__main__":
    sys.exit(main())

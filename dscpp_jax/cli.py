"""Command line: `python -m dscpp_jax.cli train|eval|plot` (the Makefile wraps it).

    python -m dscpp_jax.cli train --env point_u_maze --algo mb_dscpp --seed 0
    python -m dscpp_jax.cli train --resume runs/point_u_maze-mb_dscpp-s0-...
    python -m dscpp_jax.cli eval --run runs/<run> [--episodes 16] [--starts "9,9;-9,-9"]
    python -m dscpp_jax.cli plot runs/<run> [runs/<other> ...] [--out DIR]
    python -m dscpp_jax.cli video --run runs/<run> [--episodes 1] [--camera both] [--every 1]

Any Config field can be overridden with `--set name=value` (repeatable). Ctrl-C saves a checkpoint
and exits; `--resume RUN_DIR` continues exactly from the last checkpoint.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
from typing import Any, Optional

import jax
import numpy as np

from dscpp_jax import compare, diagnose, envs, group_train, plots, video
from dscpp_jax import seed_group as SG
from dscpp_jax.config import ALGOS, PRESETS, SUBGOALS, Config, flat_name, parse_value, preset
from dscpp_jax.envs import ant_maze
from dscpp_jax.evaluate import evaluate
from dscpp_jax.host_loop import (TrainingDiverged, final_evaluation, notes_beyond_paper,
                                 state_done, train, write_error)
from dscpp_jax.run_dir import is_group_dir, load_run, saved_config
from dscpp_jax.run_logging import RunDirError, load_config, os_error_fix, read_config, \
    write_config, wandb_missing_error
# use_fusion_autotuner_off and load_run stay importable from here for callers of older versions
from dscpp_jax.runtime import (COMPILE_CACHE_ENV, DEFAULT_COMPILE_CACHE,  # noqa: F401
                               use_compile_cache, use_fusion_autotuner_off, use_xla_flags)
from dscpp_jax.trainer import resolve_physics

# ------------------------------------------------------------------------------------------------
# Config from arguments
# ------------------------------------------------------------------------------------------------
def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """`--set name=value` items (a field by its flat or its `section.field` name) as {flat name:
    value}, each value parsed as the field's type."""
    out: dict[str, Any] = {}
    for p in pairs or []:
        if "=" not in p:
            raise ValueError(f"--set expects name=value, got {p!r}")
        k, v = p.split("=", 1)
        k = k.strip().replace("-", "_")
        value = parse_value(k, v.strip())
        out[flat_name(k)] = value
    return out


DEFAULT_ENV, DEFAULT_ALGO, DEFAULT_SEED, DEFAULT_PRESET = "point_u_maze", "mb_dscpp", 0, "fast"
"""What `train` uses where --env, --algo, --seed, --preset are not given (a fresh run)."""

FLAG_FIELDS = (("num_envs", "--num-envs"), ("steps_per_iter", "--steps-per-iter"),
               ("total_env_steps", "--total-steps"), ("total_episodes", "--total-episodes"),
               ("eval_every", "--eval-every"), ("eval_episodes", "--eval-episodes"),
               ("checkpoint_every", "--checkpoint-every"), ("subgoal", "--subgoal"))
"""Config fields that `train` has a flag of its own for (field, flag)."""

RESUME_APPLIED = ("total_env_steps", "total_episodes", "eval_every", "eval_episodes",
                  "checkpoint_every", "keep_checkpoints")
"""Config fields a --resume may change (the schedule and the host's cadences); they are
recorded in config.json. Every other field is fixed by the checkpoint."""


def config_from_args(args) -> Config:
    kw = parse_overrides(args.set)
    for name, _ in FLAG_FIELDS:
        v = getattr(args, name, None)
        if v is not None:
            kw[name] = v
    seed = getattr(args, "seed", None)
    kw["seed"] = DEFAULT_SEED if seed is None else seed
    if getattr(args, "physics", None):
        kw["physics"] = args.physics
    cfg = preset(getattr(args, "preset", None) or DEFAULT_PRESET,
                 getattr(args, "env", None) or DEFAULT_ENV,
                 getattr(args, "algo", None) or DEFAULT_ALGO, **kw)
    cfg.validate()
    cfg = resolve_physics(cfg)   # record the back end that will run
    envs.make(cfg.env)   # unknown env names fail here, before anything is compiled
    return cfg


def resume_changes(args, saved: Config, group: bool = False) -> dict:
    """The config changes that `train --resume` with these flags asks of the run saved as
    `saved`: the fields of `RESUME_APPLIED` that a flag or `--set` gives. Any other flag or field
    that the checkpoint fixes (env, algo, seed, num_envs, ...) is accepted when it equals the
    saved value and refused (ValueError, naming each) when it differs; --preset, --overwrite and a
    --run-dir other than the resumed one are refused too. Nothing is ignored."""
    given: dict[str, tuple] = {}   # field -> (value, how it was given)
    for k, v in parse_overrides(getattr(args, "set", None)).items():
        given[k] = (v, f"--set {k}={v}")
    for name, flag in FLAG_FIELDS + (("env", "--env"), ("algo", "--algo")):
        v = getattr(args, name, None)
        if v is not None:
            given[name] = (v, f"{flag} {v}")
    if getattr(args, "seed_given", False):
        given["seed"] = (args.seed, f"--seed {args.seed}")
    physics = getattr(args, "physics", None)
    if physics is not None and physics != "auto":   # auto: whatever the run was given
        given["physics"] = (physics, f"--physics {physics}")
    elif "physics" in given and given["physics"][0] == "auto":
        del given["physics"]
    problems = []
    if getattr(args, "preset", None) is not None:
        problems.append(f"--preset {args.preset} (a preset picks a new run's config; the resumed "
                        f"run keeps its own)")
    if getattr(args, "overwrite", False):
        problems.append("--overwrite (it starts the run over; --resume continues it)")
    run_dir = getattr(args, "run_dir", None)
    if run_dir is not None and os.path.abspath(run_dir) != os.path.abspath(args.resume):
        problems.append(f"--run-dir {run_dir} (the resumed run stays in {args.resume})")
    changes = {}
    for k, (v, how) in given.items():
        if k in RESUME_APPLIED:
            changes[k] = v
            continue
        if group and k == "seed":
            problems.append(f"{how} (a seed group continues its own seeds)")
            continue
        current = saved.get(k)
        if v != current:
            problems.append(f"{how} (the run has {k}={current})")
    if problems:
        raise ValueError(
            f"--resume cannot change {'; '.join(problems)}. The checkpoint fixes the state's "
            f"shapes and the algorithm; on resume only these may change: --total-steps, "
            f"--total-episodes, --eval-every, --eval-episodes, --checkpoint-every, --set "
            f"keep_checkpoints=N. Start a new run for anything else")
    return changes


def parse_starts(text: Optional[str]):
    if not text:
        return None
    pts = []
    for part in text.replace(" ", "").split(";"):
        if part:
            try:
                x, y = part.split(",")
                pts.append([float(x), float(y)])
            except ValueError:
                raise ValueError(f"--starts expects x,y pairs separated by ';' (e.g. "
                                 f"--starts \"8,8;0,4\"), got {part!r} in {text!r}") from None
    return pts


def cmd_eval(args) -> int:
    starts = parse_starts(args.starts)   # a typo here fails before anything loads
    if is_group_dir(args.run):
        return _eval_group(args, starts)
    cfg, state = load_run(args.run, args.step)
    key = jax.random.PRNGKey(args.seed)
    summary, res = evaluate(state, key, args.episodes, starts, explore=args.explore)
    summary = _eval_record(summary, state.counters, res, starts, args.explore)
    name = _eval_name(args, starts)
    out_json = os.path.join(args.run, f"{name}.json")
    try:
        with open(out_json, "w") as f:
            json.dump(summary, f, indent=2)
    except OSError as e:
        raise write_error(args.run, e, f"write {name}.json") from None
    print(json.dumps({k: v for k, v in summary.items() if "option_success/" not in k
                      or v == v}, indent=2))
    if not args.no_plot:
        path = os.path.join(args.run, f"{name}_trajectory.png")
        try:
            plots.plot_trajectory(cfg, res, path, title=f"{cfg.env} {cfg.algo} (iteration "
                                  f"{summary['iteration']})")
        except OSError as e:
            raise write_error(args.run, e, f"write {name}_trajectory.png") from None
        print(f"wrote {out_json} and {path}")
    return 0


def _eval_record(summary: dict, counters, res, starts, explore: bool) -> dict:
    """An evaluation's JSON record: the summary, where the run stood (`counters` of one seed),
    per-start outcomes with `starts`, and whether it acted with exploration noise."""
    out = dict(summary, iteration=int(counters.iteration), env_steps=int(counters.env_steps),
               episodes_trained=int(counters.episodes))
    if starts is not None:
        out["starts"] = starts
        out["steps_per_start"] = np.asarray(res.steps).tolist()
        out["success_per_start"] = np.asarray(res.success).astype(int).tolist()
    if explore:
        out["explore"] = True
    return out


def _eval_name(args, starts) -> str:
    """eval.json is the deterministic evaluation of the latest checkpoint; other kinds get names
    of their own (eval_starts, eval_explore, eval_stepN, combined), so they never overwrite it."""
    return ("eval" + ("_starts" if starts else "") + ("_explore" if args.explore else "")
            + (f"_step{args.step}" if args.step is not None else ""))


def _eval_group(args, starts) -> int:
    """`eval --run GROUP_DIR`: every seed of the group in one call; each seed's numbers equal
    those of `eval --run GROUP_DIR/sN` with the same flags. Writes each seed's JSON (and
    trajectory plot) into its directory and prints one line per seed."""
    seeds = group_train.read_group(args.run)["seeds"]
    cfg, states = group_train.load_group(args.run, args.step)
    summ, res = SG.evaluate_group(states, jax.random.PRNGKey(args.seed), args.episodes, starts,
                                  explore=args.explore)
    counters = SG.to_host(states.counters)
    name = _eval_name(args, starts)
    rates = []
    for i, seed in enumerate(seeds):
        one = SG.index_tree(res, i, len(seeds))
        summary = _eval_record(summ[i], SG.index_tree(counters, i, len(seeds)), one, starts,
                               args.explore)
        summary["seed"] = int(seed)
        d = group_train.seed_dir(args.run, seed)
        try:
            with open(os.path.join(d, f"{name}.json"), "w") as f:
                json.dump(summary, f, indent=2)
            if not args.no_plot:
                plots.plot_trajectory(cfg.override(seed=int(seed)), one,
                                      os.path.join(d, f"{name}_trajectory.png"),
                                      title=f"{cfg.env} {cfg.algo} seed {seed} (iteration "
                                            f"{summary['iteration']})")
        except OSError as e:
            raise write_error(d, e, f"write {name}.json") from None
        rate = summary["eval/success_rate"]
        rates.append(rate)
        weak = [f"{k.split('/')[-1]}:{v:.2f}" for k, v in summary.items()
                if k.startswith("eval/option_success/") and v == v and v < 0.8]
        print(f"seed {seed}: success {rate:.2f} at iteration {summary['iteration']} "
              f"({summary['episodes_trained']} episodes); options below 0.8: "
              f"{' '.join(weak) if weak else 'none'}")
    r = np.asarray(rates)
    se = r.std(ddof=1) / np.sqrt(len(r)) if len(r) > 1 else 0.0
    print(f"{len(r)} seeds: success {r.mean():.2f} +- {se:.2f} (standard error); wrote {name}.json "
          f"in each seed's directory")
    return 0


def _video_options(args) -> dict:
    cams = ("topdown", "follow") if args.camera == "both" else (args.camera,)
    return dict(cameras=cams, width=args.width, height=args.height, fps=args.fps,
                every=args.every, max_steps=args.max_steps, crf=args.crf)


def write_videos(cfg, state, run_dir: str, out: Optional[str] = None, episodes: int = 1,
                 starts=None, seed: int = 0, **options) -> dict:
    """Render evaluation episodes of `state` to MP4 under `out` (default RUN_DIR/videos)."""
    out = out or os.path.join(run_dir, "videos")
    paths = video.render_run(cfg, state, out, episodes=episodes, starts=starts, seed=seed,
                             **options)
    for k, p in paths.items():
        print(f"{k}: {p}")
    return paths


def cmd_video(args) -> int:
    if args.record_only and args.from_record:
        raise ValueError("--record-only rolls out, --from-record draws a recording: give one")
    opts = _video_options(args)
    out = args.out or os.path.join(args.run, "videos")
    if args.record_only:   # roll out here, draw elsewhere: needs neither OpenGL nor ffmpeg
        video.check_options(**opts)
        cfg, state = load_run(args.run, args.step)
        eps, meta = video.record_run(cfg, state, args.episodes, parse_starts(args.starts),
                                     args.seed, opts["max_steps"])
        print(f"record: {video.save_record(os.path.join(out, video.RECORD_FILE), eps, meta)}")
        return 0
    try:
        video.select_gl_backend()   # before JAX starts threads, and before anything compiles
        video.check_encoder()
        video.check_options(**opts)
    except video.VideoError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.from_record:   # the run's config is all that drawing a recording needs
        path = (os.path.join(args.run, "videos", video.RECORD_FILE)
                if args.from_record == "-" else args.from_record)
        eps, meta = video.load_record(path)
        opts.pop("max_steps")
        paths = video.render_record(load_config(args.run), eps, meta, out, **opts)
        for k, p in paths.items():
            print(f"{k}: {p}")
        return 0
    cfg, state = load_run(args.run, args.step)
    write_videos(cfg, state, args.run, args.out, args.episodes, parse_starts(args.starts),
                 args.seed, **opts)
    return 0


def _add_video_args(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """Video options (`prefix` "video-" for `train`, whose --seed/--episodes mean other things)."""
    p.add_argument(f"--{prefix}camera", dest="camera", default="both",
                   choices=("topdown", "follow", "both"),
                   help="top-down view of the whole maze, a camera following the agent, or both "
                        "(one MP4 each)")
    p.add_argument(f"--{prefix}width", dest="width", type=int, default=480)
    p.add_argument(f"--{prefix}height", dest="height", type=int, default=480)
    p.add_argument(f"--{prefix}fps", dest="fps", type=float, default=30.0,
                   help="frames per second (an env step is 0.1 s: 10 is real time)")
    p.add_argument(f"--{prefix}every", dest="every", type=int, default=1, metavar="K",
                   help="draw every K-th step (and the last): K times shorter, smaller files")
    p.add_argument(f"--{prefix}max-steps", dest="max_steps", type=int, default=None,
                   help="cut episodes after this many steps (default: the episode length)")
    p.add_argument(f"--{prefix}crf", dest="crf", type=int, default=23,
                   help="H.264 quality: 18 near lossless .. 28 smaller files")


def cmd_plot(args) -> int:
    out = args.out or (os.path.join(args.runs[0], "plots") if len(args.runs) == 1 else "plots")
    try:
        paths = plots.plot_runs(args.runs, out, with_state=not args.curves_only,
                                trajectory=not args.regions_only)
    except OSError as e:
        if isinstance(e, ValueError):
            raise
        raise RunDirError(f"could not write the plots to {out} ({e.strerror or e}). Fix: "
                          f"{os_error_fix(e, out)}, or pick another folder with --out DIR"
                          ) from None
    for p in paths:
        print(p)
    return 0


def cmd_diagnose(args) -> int:
    rows = diagnose.diagnose(args.runs)
    print(diagnose.format_table(rows))
    print()
    print(diagnose.format_summary(rows))
    print(diagnose.format_means(rows))
    return 0


def cmd_compare(args) -> int:
    result = compare.compare(args.runs, levels=args.levels, mature=args.mature)
    print(compare.format_table(result))
    if args.json:
        compare.write_json(result, args.json)
        print(f"numbers: {args.json}")
    return 0


def cmd_train(args) -> int:
    if getattr(args, "seeds", None) is not None or _resumes_group(args) or _distributed(args):
        return cmd_train_group(args)
    wandb = None
    if args.wandb:
        missing = wandb_missing_error()
        if missing:
            raise ValueError(missing)
        wandb = {"project": args.wandb_project, "mode": args.wandb_mode}
    if args.video:   # bad video options fail now, not after training
        try:
            video.check_options(**_video_options(args))
        except video.VideoError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    if args.resume:
        cfg = load_config(args.resume)
        cfg = cfg.override(**resume_changes(args, cfg))
        run_dir = args.resume
    else:
        cfg = config_from_args(args)
        run_dir = args.run_dir
    try:
        state, run_dir = train(cfg, run_dir, resume=bool(args.resume), time_budget=args.time_budget,
                               progress=not args.no_progress, wandb=wandb,
                               overwrite=args.overwrite, count_process=FROM_COMMAND_LINE)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        quiet_after_error()
        return 3
    if args.resume:
        payload = read_config(run_dir)
        try:
            write_config(run_dir, cfg.to_dict(), {k: v for k, v in payload.items()
                                                  if k not in ("config", "versions",
                                                               "config_defaults")})
        except OSError as e:
            raise write_error(run_dir, e, "update config.json") from None
    if not state_done(cfg, state):   # the final evaluation belongs to the schedule's end
        print(f"run: {run_dir}\nstopped at iteration {int(state.counters.iteration)} "
              f"({int(state.counters.env_steps)} env steps, {int(state.counters.episodes)} "
              f"episodes) before the end of its schedule; continue with `train --resume "
              f"{run_dir}`, evaluate with `eval --run {run_dir}`")
        return 0
    ev, res = final_evaluation(state, run_dir)
    if args.plot:
        plots.plot_run(run_dir, cfg, state, res)
    if args.video:
        try:
            write_videos(cfg, state, run_dir, episodes=args.video_episodes,
                         **_video_options(args))
        except video.VideoError as e:   # the run is saved; only its video is missing
            print(f"error: no video: {e}; render it later with: make video RUN={run_dir}",
                  file=sys.stderr)
    print(f"run: {run_dir}\nenv steps {int(state.counters.env_steps)}, episodes "
          f"{int(state.counters.episodes)}, eval success {ev['eval/success_rate']:.2f}, "
          f"options {int(ev['eval/num_options'])}")
    verdict = diagnose.chain_verdict(cfg, run_dir)
    if verdict:
        print(f"chain: {verdict} (python -m dscpp_jax.cli diagnose {run_dir})")
    return 0


# ------------------------------------------------------------------------------------------------
# Seed groups: `train --seeds 0-7` (dscpp_jax.seed_group, dscpp_jax.group_train)
# ------------------------------------------------------------------------------------------------
class _SeedGiven(argparse.Action):
    """--seed that remembers it was given (so that --seed with --seeds is an error)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.seed_given = True


def _resumes_group(args) -> bool:
    return bool(args.resume) and is_group_dir(args.resume)


def _distributed(args) -> bool:
    return bool(getattr(args, "coordinator", None) or getattr(args, "distributed", False))


def _add_group_arguments(t: argparse.ArgumentParser) -> None:
    t.add_argument("--seeds", default=None, metavar="LIST",
                   help="train a seed group in one program, e.g. 0-7 or 0-3,7,9 (one run directory "
                        "per seed inside runs/<env>-<algo>-g<seeds>-<time>/)")
    t.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="multi-host seed group: address of process 0 (jax.distributed)")
    t.add_argument("--num-processes", dest="num_processes", type=int, default=None)
    t.add_argument("--process-id", dest="process_id", type=int, default=None)
    t.add_argument("--distributed", action="store_true",
                   help="join a multi-host run that JAX detects itself (SLURM, Open MPI, ...) or "
                        "that JAX_COORDINATOR_ADDRESS / JAX_NUM_PROCESSES / JAX_PROCESS_ID describe")


def cmd_train_group(args) -> int:
    if args.seeds is None and not args.resume:
        raise ValueError("--coordinator / --distributed train a seed group: add --seeds LIST")
    if args.seeds is not None and not args.resume:   # bad input fails before any device is used
        if getattr(args, "seed_given", False):
            raise ValueError("give either --seed N (one run) or --seeds LIST (a seed group), "
                             "not both")
        seeds = SG.parse_seeds(args.seeds)
    if _distributed(args):   # before anything touches a device
        SG.initialize_distributed(args.coordinator, args.num_processes, args.process_id)
    if args.resume:
        if not is_group_dir(args.resume):
            raise ValueError(f"{args.resume} is not a seed group (no {group_train.GROUP_FILE}); "
                             f"resume a single run without --seeds")
        if args.seeds is not None:
            raise ValueError("--resume of a seed group continues its own seeds; drop --seeds")
        saved = Config.from_dict(group_train.read_group(args.resume)["config"])
        cfg, seeds = group_train.resume_config(args.resume,
                                               resume_changes(args, saved, group=True))
        group_dir = args.resume
    else:
        cfg = config_from_args(args)
        group_dir = args.run_dir
    for note in notes_beyond_paper(cfg):
        print(note, file=sys.stderr)
    try:
        states, group_dir, summaries = group_train.train_group(
            cfg, seeds, group_dir, resume=bool(args.resume), time_budget=args.time_budget,
            progress=not args.no_progress, plot=plots.plot_group if args.plot else None,
            overwrite=args.overwrite, count_process=FROM_COMMAND_LINE)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        quiet_after_error()
        return 3
    c = SG.to_host(states.counters)   # a collective in a multi-process run: every process
    if jax.process_index() != 0:
        return 0
    if args.resume:
        group_train.update_configs(group_dir, cfg, seeds)
    if summaries is None:   # stopped before the end of the schedule: no final evaluation
        print(f"group: {group_dir} stopped before the end of its schedule; continue with "
              f"`train --resume {group_dir}`, evaluate with `eval --run {group_dir}`")
        for i, s in enumerate(seeds):
            print(f"  s{s}: env steps {int(c.env_steps[i])}, episodes {int(c.episodes[i])}")
        return 0
    succ = np.array([s["eval/success_rate"] for s in summaries])
    print(f"group: {group_dir} ({len(seeds)} seeds on {jax.device_count()} devices)")
    for i, s in enumerate(seeds):
        verdict = diagnose.chain_verdict(cfg, group_train.seed_dir(group_dir, s))
        print(f"  s{s}: env steps {int(c.env_steps[i])}, episodes {int(c.episodes[i])}, eval "
              f"success {succ[i]:.2f}, options {int(summaries[i]['eval/num_options'])}"
              + (f", chain: {verdict}" if verdict else ""))
    print(f"eval success mean {succ.mean():.2f} min {succ.min():.2f} max {succ.max():.2f}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m dscpp_jax.cli",
                                description="Robust Deep Skill Chaining (DSC++) in JAX")
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train", help="train a run (or continue one with --resume)")
    t.add_argument("--env", default=None, help=f"default: {DEFAULT_ENV}")
    t.add_argument("--algo", default=None, choices=ALGOS, help=f"default: {DEFAULT_ALGO}")
    t.add_argument("--seed", type=int, default=None, action=_SeedGiven,
                   help=f"default: {DEFAULT_SEED}")
    t.add_argument("--preset", default=None, choices=PRESETS, help=f"default: {DEFAULT_PRESET}")
    t.add_argument("--subgoal", default=None, choices=SUBGOALS)
    t.add_argument("--physics", default=None, choices=("auto", "jax", "warp"),
                   help="ant physics back end: warp (MuJoCo Warp, default on a GPU with warp-lang "
                        "installed), jax (MJX; default elsewhere)")
    t.add_argument("--num-envs", dest="num_envs", type=int, default=None)
    t.add_argument("--steps-per-iter", dest="steps_per_iter", type=int, default=None)
    t.add_argument("--total-steps", dest="total_env_steps", type=int, default=None)
    t.add_argument("--total-episodes", dest="total_episodes", type=int, default=None,
                   help="also stop once this many episodes finished (0: no episode limit)")
    t.add_argument("--eval-every", dest="eval_every", type=int, default=None)
    t.add_argument("--eval-episodes", dest="eval_episodes", type=int, default=None)
    t.add_argument("--checkpoint-every", dest="checkpoint_every", type=int, default=None)
    t.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override any Config field (repeatable)")
    t.add_argument("--run-dir", default=None, help="default: runs/<env>-<algo>-s<seed>-<time>")
    t.add_argument("--resume", default=None, metavar="RUN_DIR",
                   help="continue a run from its last checkpoint; flags the checkpoint fixes "
                        "(env, algo, seed, num-envs, ...) must equal the run's, the schedule's "
                        "and cadences' (totals, eval, checkpoint) are applied")
    t.add_argument("--overwrite", action="store_true",
                   help="start over in a --run-dir that holds an earlier run: its checkpoints "
                        "and logs are deleted first (without this flag such a directory is "
                        "refused)")
    t.add_argument("--time-budget", type=_seconds, default=None, metavar="SECONDS",
                   help="wall-clock from the start of the process: before an iteration that "
                        "would end past it, checkpoint and stop (no final evaluation)")
    t.add_argument("--no-progress", action="store_true",
                   help="no progress bar; print one line per evaluation instead")
    t.add_argument("--plot", action="store_true",
                   help="at the end, write curves/trajectory/classifier plots to RUN_DIR/plots")
    det_help = ("deterministic XLA GPU kernels, so one seed gives the same run twice on a GPU with "
                "--physics jax (1.1-1.3x the time per iteration on the ant). Default: on, except "
                "with MuJoCo Warp physics (the GPU default), which does not repeat either way")
    t.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help=det_help)
    cache_help = ("directory of compiled programs reused across runs, resumes and evaluations "
                  f"(default: ${COMPILE_CACHE_ENV}, else {DEFAULT_COMPILE_CACHE}; 'off': none)")
    t.add_argument("--compile-cache", default=None, metavar="DIR", help=cache_help)
    _add_group_arguments(t)
    t.add_argument("--wandb", action="store_true",
                   help="also log to Weights & Biases (pip install 'dscpp_jax[wandb]'); a resumed "
                        "run continues the same wandb run")
    t.add_argument("--wandb-project", default="dscpp_jax", metavar="NAME")
    t.add_argument("--wandb-mode", default=None, choices=("online", "offline", "disabled"),
                   help="default: $WANDB_MODE, else online")
    t.add_argument("--video", action="store_true",
                   help="at the end, render evaluation episodes to MP4 in RUN_DIR/videos")
    t.add_argument("--video-episodes", dest="video_episodes", type=int, default=1)
    _add_video_args(t, prefix="video-")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="evaluate a run's latest checkpoint (a seed group's: every "
                                    "seed in one call)")
    e.add_argument("--run", required=True, help="a run directory, a seed directory of a group, "
                                                "or a group directory (all its seeds)")
    e.add_argument("--episodes", type=int, default=16)
    e.add_argument("--starts", default=None, help='start positions "x,y;x,y" (default: task start)')
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--no-plot", action="store_true")
    e.add_argument("--step", type=int, default=None,
                   help="checkpoint step (default: the latest; writes eval_stepN.json)")
    e.add_argument("--explore", action="store_true",
                   help="act with training's action noise (a diagnostic; writes eval_explore.json)")
    e.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help=det_help)
    e.add_argument("--compile-cache", default=None, metavar="DIR", help=cache_help)
    e.set_defaults(func=cmd_eval)

    v = sub.add_parser("video", help="render evaluation episodes of a run's checkpoint to MP4")
    v.add_argument("--run", required=True)
    v.add_argument("--episodes", type=int, default=1)
    v.add_argument("--starts", default=None, help='start positions "x,y;x,y" (default: task start)')
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--step", type=int, default=None, help="checkpoint step (default: the latest)")
    v.add_argument("--out", default=None, help="output directory (default: RUN/videos)")
    v.add_argument("--record-only", action="store_true",
                   help="roll out and save the episodes to OUT/episodes.npz without drawing "
                        "(no OpenGL or ffmpeg needed: e.g. on a GPU training host)")
    v.add_argument("--from-record", nargs="?", const="-", default=None, metavar="FILE",
                   help="draw episodes saved by --record-only (default RUN/videos/episodes.npz) "
                        "with RUN's config; needs no checkpoint")
    _add_video_args(v)
    v.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help=det_help)
    v.add_argument("--compile-cache", default=None, metavar="DIR", help=cache_help)
    v.set_defaults(func=cmd_video)

    pl = sub.add_parser("plot", help="learning curves (one or many runs) + trajectory/classifier plots")
    pl.add_argument("runs", nargs="+",
                    help="run directories; a seed group's directory stands for its seeds; "
                         "LABEL=DIR names the curve DIR belongs to. Runs without a checkpoint "
                         "(results copies) get their curves only")
    pl.add_argument("--out", default=None)
    pl.add_argument("--curves-only", action="store_true")
    pl.add_argument("--regions-only", action="store_true",
                    help="curves and the options' regions, but no evaluation episodes for the "
                         "trajectory plot (seconds instead of minutes on the ant)")
    pl.set_defaults(func=cmd_plot)

    dg = sub.add_parser("diagnose", help="why each run's skill chain fails from the start (falls, "
                        "weak links, a full table, a stalled link), from metrics.csv and eval.json")
    dg.add_argument("runs", nargs="+",
                    help="run directories of finished runs; a seed group's directory stands for "
                         "its seeds")
    dg.set_defaults(func=cmd_diagnose)

    cp = sub.add_parser("compare", help="settings side by side: final success, iterations to an "
                        "in-band level, chain growth, falls and seconds per iteration of groups "
                        "of runs, from metrics.csv and eval.json")
    cp.add_argument("runs", nargs="+", metavar="[LABEL=]DIR",
                    help="run or seed-group directories; entries with one LABEL are pooled "
                         "into one column (a plain DIR is its own column, named after it)")
    cp.add_argument("--levels", type=float, nargs="+", default=[0.1, 0.5, 0.9],
                    help="in-band success levels: the first iteration each run reached them")
    cp.add_argument("--mature", type=int, nargs="+", default=[1, 3, 5, 9],
                    help="chain sizes: the first iteration with this many mature options")
    cp.add_argument("--json", default=None, metavar="PATH",
                    help="also write the numbers (per run and per column) as JSON")
    cp.set_defaults(func=cmd_compare)
    return p


def _seconds(text: str) -> float:
    """argparse type: a number of seconds > 0 (a budget of 0 or less would stop after one
    iteration without saying why)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text}: give a number of seconds > 0")
    return v


def _saved_config_of(args) -> Optional[dict]:
    """The saved config of the command's `--resume` / `--run` directory; None without one."""
    saved_dir = getattr(args, "resume", None) or getattr(args, "run", None)
    return saved_config(saved_dir) if saved_dir else None


def runs_on_warp(args) -> bool:
    """Whether the command's ant physics will be MuJoCo Warp: `--physics` (else `--set physics=`),
    else the saved config of `--resume` / `--run`, else "auto", which picks Warp where warp-lang
    is installed (the GPU default). Decided before JAX starts, so that `--deterministic`'s
    default can follow it; point-mass twins have no MuJoCo physics."""
    env = getattr(args, "env", "")
    env = DEFAULT_ENV if env is None else env   # train's default
    physics = None
    for item in getattr(args, "set", None) or []:
        k, _, v = item.partition("=")
        if k.strip().replace("-", "_") == "physics":
            physics = v.strip()
    physics = getattr(args, "physics", None) or physics   # as config_from_args: --physics wins
    saved = _saved_config_of(args)
    if saved is not None:
        env = saved.get("env", "")
        physics = physics or saved.get("physics", "auto")
    if env.startswith("point_"):
        return False
    physics = physics or "auto"
    if physics != "auto":
        return physics == "warp"
    return ant_maze.warp_available()


def deterministic_default(args) -> bool:
    """`--deterministic`'s default: deterministic XLA kernels, except where the ant physics is
    MuJoCo Warp. Warp's own kernels do not repeat on a GPU either way, so there the switch buys
    no repeatability and only costs time (docs/reproducibility.md)."""
    return not runs_on_warp(args)


def deterministic_choice(args) -> bool:
    """`--deterministic` / `--no-deterministic` where given, else `deterministic_default`."""
    on = getattr(args, "deterministic", None)
    return deterministic_default(args) if on is None else on


def quiet_after_error() -> None:
    """Once a command has printed its one-line error, keep the rest of the process quiet: the
    same failure raised again in library threads (orbax's, tensorboardX's writer) or in exit
    handlers (a log writer flushing onto the full disk) is not printed after that line. Only
    for `main()` run as the process's command, which ends right after."""
    if not FROM_COMMAND_LINE:
        return
    sys.unraisablehook = lambda unraisable: None
    threading.excepthook = lambda hook_args: None


FROM_COMMAND_LINE = False
"""Set by `main()` run as the process's command (no argv given): only then does a start-up
record count the process's own start (interpreter, imports) as part of the command."""


def main(argv: Optional[list[str]] = None) -> int:
    global FROM_COMMAND_LINE
    FROM_COMMAND_LINE = argv is None
    args = build_parser().parse_args(argv)
    if hasattr(args, "deterministic"):
        use_xla_flags(deterministic_choice(args))
    if hasattr(args, "compile_cache"):
        use_compile_cache(args.compile_cache)
    try:
        return args.func(args)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        quiet_after_error()
        return 2
    except BrokenPipeError:   # the reader of stdout left (`... | head`): stop quietly
        try:   # no second BrokenPipeError when the interpreter flushes stdout at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return 141
    except OSError as e:   # a file the command reads or writes; the message names which
        where = getattr(e, "filename", None) or "the run directory"
        print(f"error: {e.strerror or e} ({where}). Fix: {os_error_fix(e, str(where))}",
              file=sys.stderr)
        quiet_after_error()
        return 2


if __name__ == "__main__":
    sys.exit(main())

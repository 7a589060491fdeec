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
import dataclasses
import json
import os
import signal
import sys
import time
from typing import Any, Optional

from dscpp_jax.config import ALGOS, PRESETS, SUBGOALS, Config, parse_value, preset
from dscpp_jax import diagnose
from dscpp_jax.host_loop import Budget, TrainingDiverged, nonfinite_parts, on_main_thread
from dscpp_jax.run_dir import check_fresh, lock_run_dir
from dscpp_jax.run_logging import RunDirError


# ------------------------------------------------------------------------------------------------
# Config from arguments
# ------------------------------------------------------------------------------------------------
def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """`--set name=value` items as {field: value}, each value parsed as the field's type."""
    out: dict[str, Any] = {}
    for p in pairs or []:
        if "=" not in p:
            raise ValueError(f"--set expects name=value, got {p!r}")
        k, v = p.split("=", 1)
        k = k.strip().replace("-", "_")
        out[k] = parse_value(k, v.strip())
    return out


DEFAULT_ENV, DEFAULT_ALGO, DEFAULT_SEED, DEFAULT_PRESET = "point_u_maze", "mb_dscpp", 0, "fast"
"""What `train` uses where --env, --algo, --seed, --preset are not given (a fresh run)."""

FLAG_FIELDS = (("num_envs", "--num-envs"), ("steps_per_iter", "--steps-per-iter"),
               ("total_env_steps", "--total-steps"), ("total_episodes", "--total-episodes"),
               ("eval_every", "--eval-every"), ("eval_episodes", "--eval-episodes"),
               ("checkpoint_every", "--checkpoint-every"), ("subgoal", "--subgoal"))
"""Config fields that `train` has a flag of its own for (field, flag)."""

RESUME_APPLIED = ("total_env_steps", "total_episodes", "eval_every", "eval_episodes",
                  "checkpoint_every", "keep_checkpoints", "log_every")
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
    from dscpp_jax.trainer import resolve_physics   # record the back end that will run
    cfg = resolve_physics(cfg)
    from dscpp_jax import envs  # unknown env names fail here, before anything is compiled
    envs.make(cfg.env)
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
        current = getattr(saved, k, None)
        if v != current:
            problems.append(f"{how} (the run has {k}={current})")
    if problems:
        raise ValueError(
            f"--resume cannot change {'; '.join(problems)}. The checkpoint fixes the state's "
            f"shapes and the algorithm; on resume only these may change: --total-steps, "
            f"--total-episodes, --eval-every, --eval-episodes, --checkpoint-every, --set "
            f"keep_checkpoints=N, --set log_every=N. Start a new run for anything else")
    return changes


def frontier_note(cfg: Config) -> str:
    """One line for a run whose skill chain uses the chain's frontier (beyond the paper; on in the
    ant preset for the medium and large mazes and for MB-DSC++, MF-DSC++ and DSC on four rooms),
    saying how to train the paper's rule instead; "" otherwise."""
    if not cfg.frontier_on:
        return ""
    return (f"{cfg.env}: the chain's frontier is on (beyond the paper: frontier_start_prob="
            f"{cfg.frontier_start_prob:g}, frontier_parent={str(cfg.frontier_parent).lower()}); "
            f"the paper's rule: --set frontier_start_prob=0 --set frontier_parent=false")


def medium_td3_note(cfg: Config) -> str:
    """One line for a model-free run on the ant medium maze with that maze's TD3 (HER `future`
    at 0.8 and twice the action penalty; beyond the paper, `config.MEDIUM_MODEL_FREE_TD3`),
    saying how to train the other mazes' TD3 instead; "" otherwise."""
    from dscpp_jax.config import MEDIUM_MODEL_FREE_TD3, MODEL_BASED_ALGOS, preset
    if cfg.env != "medium" or cfg.algo in MODEL_BASED_ALGOS or any(
            getattr(cfg, k) != v for k, v in MEDIUM_MODEL_FREE_TD3.items()):
        return ""

    def fmt(v):
        return f"{v:g}" if isinstance(v, float) else str(v)

    other = preset("fast", "four_rooms", cfg.algo)    # what the other ant mazes train with
    sets = ", ".join(f"{k}={fmt(v)}" for k, v in MEDIUM_MODEL_FREE_TD3.items())
    back = " ".join(f"--set {k}={fmt(getattr(other, k))}" for k in MEDIUM_MODEL_FREE_TD3)
    return (f"{cfg.env}: the model-free learners' TD3 of this maze (beyond the paper: {sets}); "
            f"the other ant mazes': {back}")


def notes_beyond_paper(cfg: Config) -> list:
    """The lines a train call prints about what its preset adds beyond the paper."""
    return [n for n in (frontier_note(cfg), medium_td3_note(cfg)) if n]


DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def _backends_initialized() -> bool:
    """Whether JAX already uses a device in this process (then XLA_FLAGS no longer matter)."""
    try:   # a private helper of JAX's; where a version lacks it, assume no device is in use yet
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        return False
    return backends_are_initialized()


def use_deterministic_ops(on: bool) -> bool:
    """Ask XLA for deterministic GPU kernels (``XLA_FLAGS`` += ``--xla_gpu_deterministic_ops``).

    Without it, XLA's GPU scatter-adds (MuJoCo MJX's contact assembly among them) use atomics,
    and two GPU runs of one seed drift apart from the first iteration; with it MJX runs repeat bit
    for bit, at 1.1-1.3x the time per iteration on the ant (experiments/results/gpu_determinism).
    MuJoCo Warp's own kernels use atomics that this flag does not reach, so Warp runs do not
    repeat on a GPU either way. CPU runs repeat either way. XLA reads the flag when JAX first touches a device, so this only
    works before that; returns whether the flag is in effect for this process.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if not on or "xla_gpu_deterministic_ops" in flags:
        return "xla_gpu_deterministic_ops=true" in flags
    if _backends_initialized():
        import jax
        if jax.default_backend() != "gpu":
            return False   # CPU kernels repeat anyway
        print("warning: JAX already uses a device in this process; --deterministic cannot take "
              "effect (set XLA_FLAGS=--xla_gpu_deterministic_ops=true before starting Python)",
              file=sys.stderr)
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()
    return True


FUSION_AUTOTUNER_FLAG = "--xla_gpu_experimental_enable_fusion_autotuner=false"


def use_fusion_autotuner_off() -> bool:
    """Turn XLA's fusion autotuner off (``XLA_FLAGS`` += ``--xla_gpu_experimental_enable_fusion_autotuner=false``)
    unless ``XLA_FLAGS`` already sets it either way.

    That autotuner compiles each large reduction and transpose fusion a second time with Triton's
    block-level emitter and times both. Under a seed group's vmap some of those fusions become
    large enough that the Triton variants take minutes to compile, for a few per cent faster
    iterations (docs/reproducibility.md, "XLA settings"). GEMM autotuning stays
    on. Like every XLA flag it only takes effect before JAX first touches a device; returns whether
    the autotuner is off for this process.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_gpu_experimental_enable_fusion_autotuner" in flags:
        return FUSION_AUTOTUNER_FLAG.lstrip("-") in flags
    if _backends_initialized():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FUSION_AUTOTUNER_FLAG}".strip()
    return True


def use_xla_flags(deterministic: bool) -> bool:
    """The XLA flags of a run, set before JAX touches a device: the fusion autotuner off
    (`use_fusion_autotuner_off`) and deterministic kernels where asked (`use_deterministic_ops`,
    whose result this returns)."""
    use_fusion_autotuner_off()
    return use_deterministic_ops(deterministic)


COMPILE_CACHE_ENV = "DSCPP_JAX_COMPILE_CACHE"
DEFAULT_COMPILE_CACHE = os.path.join("~", ".cache", "dscpp_jax", "xla")


def use_compile_cache(path: Optional[str], min_compile_time_s: float = 1.0) -> Optional[str]:
    """Keep compiled programs in directory ``path`` (JAX's persistent compilation cache), so that
    a resumed run, or an evaluation of a config trained before, loads its programs instead of
    compiling them again (the ant's ``train_step`` takes tens of seconds to compile).

    ``None`` picks ``$DSCPP_JAX_COMPILE_CACHE``, then JAX's own ``jax_compilation_cache_dir``
    setting, then ``~/.cache/dscpp_jax/xla``; ``"off"`` (or ``""``) uses no cache. Programs that
    compile faster than ``min_compile_time_s`` are not stored. JAX decides whether to use the
    cache at its first compilation, so this only takes effect before that. Returns the directory
    in use, or None.
    """
    import jax
    if path is None:
        path = os.environ.get(COMPILE_CACHE_ENV)
    if path is None:
        path = jax.config.jax_compilation_cache_dir or DEFAULT_COMPILE_CACHE
    if not path or path.lower() == "off":
        return None
    path = os.path.abspath(os.path.expanduser(path))
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        print(f"warning: cannot use {path} as the compilation cache ({e}); compiling without it",
              file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    return path


def default_run_dir(cfg: Config, root: str = "runs") -> str:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return os.path.join(root, f"{cfg.env}-{cfg.algo}-s{cfg.seed}-{stamp}")


def _is_ant(cfg: Config) -> bool:
    return not cfg.env.startswith("point_")


# ------------------------------------------------------------------------------------------------
# Training driver (host side)
# ------------------------------------------------------------------------------------------------
def stuck_chain_warning(metrics: dict, cfg: Config, who: str = "") -> Optional[str]:
    """The warning for a chain that can no longer reach the start, or None: every row of the option
    table is in use (``options/capacity_hit``: a new option was needed and there was no room) and
    no option's initiation region holds the task start (``options/start_covered``). The original
    algorithm has no cap and would add an option; here no new link can be made, so success from
    the start stays near 0 unless a refit widens an existing region again (measured on the ant
    medium maze: ``experiments/results/paper/README.md``, "Against the falls")."""
    if metrics.get("options/capacity_hit", 0) < 0.5 or metrics.get("options/start_covered", 1) > 0.5:
        return None
    return (f"warning: {who}the option table is full (max_options={cfg.max_options}) and no "
            f"option's initiation region holds the task start any more; the chain cannot add the "
            f"link it needs, so success from the start will likely stay near 0. Restart with more "
            f"rows, e.g. --set max_options={cfg.max_options + 8}.")


def stalled_link_warning(metrics: dict, cfg: Config, who: str = "") -> Optional[str]:
    """The warning for a chain link in gestation that has failed ``diagnose.STALLED_LINK_EXECUTIONS`` or
    more executions without one success (``options/gestation_executions``,
    ``options/gestation_successes``), or None. Until it matures no new link is made, so the chain
    has stopped growing. Seen on the ant's medium maze, where such a link targeted an option in a
    dead end while that option's frontier stayed open (``experiments/results/paper/README.md``)."""
    if not diagnose.link_stalled(metrics):
        return None
    n = metrics["options/gestation_executions"]
    parent = int(metrics.get("options/gestation_parent", -1))
    return (f"warning: {who}the option in gestation (it targets option {parent}) has failed "
            f"{int(n)} executions without one success, so the chain has stopped growing there. "
            f"Its target's region is likely out of reach from where its executions start; look at "
            f"the options' regions (`plot RUN_DIR --regions-only`). docs/training.md, "
            f"\"A stalled link\", says what to try.")


def chain_warnings(metrics: dict, cfg: Config, who: str = "") -> list:
    """(kind, message) for each chain warning that holds in this iteration's metrics: the full
    table without the start (``stuck_chain_warning``) and the stalled link
    (``stalled_link_warning``). Callers print each kind once per run (per seed in a group)."""
    out = []
    for kind, fn in (("stuck", stuck_chain_warning), ("stalled", stalled_link_warning)):
        msg = fn(metrics, cfg, who)
        if msg:
            out.append((kind, msg))
    return out


def train(cfg: Optional[Config] = None, run_dir: Optional[str] = None, resume: bool = False,
          time_budget: Optional[float] = None, progress: bool = True,
          max_iterations: Optional[int] = None, initial_state=None,
          wandb: Optional[dict] = None, overwrite: bool = False):
    """Train (or resume) a run; returns (state, run_dir). Saves checkpoints and metrics.csv.

    `initial_state` (optional) replaces `init(PRNGKey(seed), cfg)` for a fresh run. `wandb`
    (optional): `{"project": ..., "mode": ...}` also logs to Weights & Biases.
    The run directory is locked for this process (`run_dir.lock_run_dir`); a fresh run refuses a
    directory that holds an earlier run unless `overwrite`, which clears it first.
    `time_budget` (seconds) counts from the start of the process for the command line, else from
    this call: the loop stops, with a checkpoint, before an iteration that would end past it.
    A directory that cannot be read or written raises a ValueError (`RunDirError`,
    `CheckpointError`) that names the fix; what was saved before stays as it was."""
    import jax
    import numpy as np

    from dscpp_jax import checkpoint as ck
    from dscpp_jax import trainer as T
    from dscpp_jax.evaluate import evaluate
    from dscpp_jax.run_logging import RunLogger, StartupClock, load_config, write_config

    clock = StartupClock(count_process=_FROM_COMMAND_LINE)
    budget = Budget(time_budget, count_process=_FROM_COMMAND_LINE)
    if resume:
        if run_dir is None:
            raise ValueError("--resume needs the run directory to continue")
        saved = load_config(run_dir)
        cfg = saved if cfg is None else cfg
    if cfg is None:
        raise ValueError("train() needs a Config (or resume=True with a run_dir)")
    cfg = T.resolve_physics(cfg.validate())
    if run_dir is None:
        run_dir = default_run_dir(cfg)
    if _is_ant(cfg):
        print(f"{cfg.env}: {'MuJoCo Warp' if cfg.physics == 'warp' else 'MJX (JAX)'} physics on "
              f"{jax.default_backend().upper()}", file=sys.stderr)
    for note in notes_beyond_paper(cfg):
        print(note, file=sys.stderr)
    try:
        lock_run_dir(run_dir)
        if not resume:
            check_fresh(run_dir, overwrite)
    except RunDirError:
        raise
    except OSError as e:
        raise _write_error(run_dir, e, "create the run directory") from None
    if _is_ant(cfg) and jax.default_backend() == "cpu":
        print(f"WARNING: {cfg.env} is an MJX ant environment meant for a GPU; on a CPU it is very "
              f"slow. Use a point-mass twin (e.g. point_{cfg.env}) for CPU runs.", file=sys.stderr)

    key = jax.random.PRNGKey(cfg.seed)
    # On MuJoCo Warp, Warp's kernels build in a thread while XLA compiles `init` and the step
    # ahead of time; `init` runs once the thread is done (see `trainer.prewarm_physics`)
    clock.mark("set-up")
    prewarm = T.prewarm_physics(cfg)
    clock.mark("env build")
    if prewarm is not None:
        T.compile_ahead(key, cfg, initial_state)
        clock.mark("XLA compile ahead (init, train_step)")
        prewarm.join()
        clock.mark("MuJoCo Warp kernels left")
    state = T.init(key, cfg) if initial_state is None else initial_state
    jax.block_until_ready(state)
    clock.mark("init")
    start_iter = 0
    if resume and ck.latest_step(run_dir) is not None:
        # the newest checkpoint that restores; damaged newer ones are reported and set aside
        state = ck.restore_state(run_dir, state, set_aside_broken=True)
        clock.mark("restore")
        start_iter = int(state.counters.iteration)
        print(f"resumed {run_dir} at iteration {start_iter} "
              f"({int(state.counters.env_steps)} env steps)", file=sys.stderr)
    else:
        env_cfg = T.make_env(cfg).config   # the physics and task constants the run trains on
        try:
            write_config(run_dir, cfg.to_dict(), {"command": " ".join(sys.argv),
                                                  "env": dataclasses.asdict(env_cfg)})
        except OSError as e:
            raise _write_error(run_dir, e, "write config.json") from None
    try:
        logger = RunLogger(run_dir, resume_iteration=start_iter,
                           wandb=None if wandb is None else {**wandb, "config": cfg.to_dict()})
    except OSError as e:
        raise _write_error(run_dir, e, "write metrics.csv") from None
    ckpt = ck.Checkpointer(run_dir, keep=cfg.keep_checkpoints)

    stop = {"flag": False}

    def on_sigint(signum, frame):
        if stop["flag"]:
            raise KeyboardInterrupt
        stop["flag"] = True
        print("\ninterrupt: finishing this iteration, saving a checkpoint, then exiting "
              "(Ctrl-C again to abort without saving)", file=sys.stderr)

    old_handler = signal.signal(signal.SIGINT, on_sigint) if on_main_thread() else None
    pbar = None
    if progress:
        try:
            from tqdm import tqdm
            pbar = tqdm(total=cfg.total_env_steps, initial=int(state.counters.env_steps),
                        unit="step", dynamic_ncols=True, desc=f"{cfg.env}/{cfg.algo}")
        except Exception:  # noqa: BLE001
            pbar = None
    t_start = time.time()
    wall0 = _previous_wall(run_dir)
    last_eval = float("nan")
    saved_iter = start_iter
    warned = set()   # chain warnings already printed (chain_warnings kinds)
    clock.mark("set-up")
    first = True
    try:
        while not _schedule_done(cfg, state):
            if max_iterations is not None and int(state.counters.iteration) - start_iter >= max_iterations:
                break
            if budget.no_room():
                print(budget.reached_text(), file=sys.stderr)
                break
            prev = state
            t0 = time.time()
            state, m = T.train_step(state)
            m = {k: float(v) for k, v in jax.device_get(m).items()}
            dt = time.time() - t0
            if first:
                first = False
                clock.mark("first iteration")
                _write_startup(clock, run_dir, pbar, iteration=int(state.counters.iteration),
                               resumed_at_iteration=start_iter, physics=cfg.physics,
                               device=str(jax.devices()[0].device_kind))
            bad = nonfinite_parts(m)
            if bad:
                it = int(prev.counters.iteration)
                ckpt.save(it, prev)
                raise TrainingDiverged(
                    f"learning diverged at iteration {it + 1}: non-finite values in {bad}. The last "
                    f"finite state was saved (iteration {it}) under {run_dir}/checkpoints. Lower the "
                    f"learning rates (td3_lr, dyn_lr) or the updates per step and resume or restart.")
            it = int(state.counters.iteration)
            row = {"iteration": it, "env_steps": m["counters/env_steps"],
                   "episodes": m["counters/episodes"], "wall_clock": wall0 + time.time() - t_start,
                   "time/iteration_s": dt,
                   "time/env_steps_per_s": cfg.steps_per_iteration_total / max(dt, 1e-9)}
            row.update({k: v for k, v in m.items() if not k.startswith("counters/")})
            if cfg.eval_every and (it % cfg.eval_every == 0 or _schedule_done(cfg, state)):
                ev, _ = evaluate(state)
                row.update(ev)
                last_eval = ev["eval/success_rate"]
                if pbar is None:
                    print(f"[{row['wall_clock']:7.0f}s] it {it} env_steps {int(row['env_steps'])} "
                          f"episodes {int(row['episodes'])} eval_success {last_eval:.2f} "
                          f"steps_to_goal {ev['eval/steps_to_goal']:.0f}{_inband_text(m)} options "
                          f"{int(m.get('options/num_options', 1))} train_success "
                          f"{m.get('train/episode_success', float('nan')):.2f} "
                          f"steps/s {row['time/env_steps_per_s']:.0f}", flush=True)
            elif pbar is None and "inband/success_rate" in m and it % INBAND_LINE_EVERY == 0:
                print(f"[{row['wall_clock']:7.0f}s] it {it} env_steps {int(row['env_steps'])} "
                      f"episodes {int(row['episodes'])}{_inband_text(m)} options "
                      f"{int(m.get('options/num_options', 1))} "
                      f"steps/s {row['time/env_steps_per_s']:.0f}", flush=True)
            logger.log(row)
            for kind, msg in chain_warnings(m, cfg, f"iteration {it}: "):
                if kind not in warned:
                    warned.add(kind)
                    (pbar.write if pbar is not None else print)(msg, file=sys.stderr)
            if pbar is not None:
                pbar.update(int(m["counters/env_steps"]) - pbar.n)
                inband = {"inband_success": _inband_rate(m)} if "inband/success_rate" in m else {}
                pbar.set_postfix(episodes=int(m["counters/episodes"]),
                                 eval_success=f"{last_eval:.2f}", **inband,
                                 options=int(m.get("options/num_options", 1)),
                                 steps_per_s=f"{row['time/env_steps_per_s']:.0f}", refresh=False)
            if cfg.checkpoint_every and it % cfg.checkpoint_every == 0:
                ckpt.save(it, state, wait=False)   # written while the next iterations run
                saved_iter = it
            budget.iteration_took(time.time() - t0)
            if stop["flag"]:
                break
        it = int(state.counters.iteration)
        if it != saved_iter or ckpt.latest_step() is None:
            t0 = time.time()
            ckpt.save(it, state)
            budget.save_took(time.time() - t0)
        if stop["flag"]:
            print(f"saved a checkpoint at iteration {it}; continue with --resume {run_dir}",
                  file=sys.stderr)
    except OSError as e:
        if isinstance(e, ck.CheckpointError):
            raise
        last = ckpt.latest_step()
        raise _write_error(run_dir, e, "write the run's logs (metrics.csv)", resume=True,
                           note=f"the last checkpoint (iteration {last}) is intact"
                           if last is not None else "") from None
    finally:
        if pbar is not None:
            pbar.close()
        ending_error = sys.exc_info()[0]   # set while an exception ends the run
        for close in (logger.close, ckpt.close):
            try:
                close()
            except Exception:  # noqa: BLE001 - never hide the error that ended the run
                if ending_error is None:
                    raise
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)
    return state, run_dir


def _write_startup(clock, run_dir: str, pbar=None, **extra) -> None:
    """Record the command's start-up in run_dir/startup.jsonl and say it in one line."""
    from dscpp_jax.run_logging import STARTUP_FILE
    try:
        clock.write(run_dir, **extra)
        where = f"; {os.path.join(run_dir, STARTUP_FILE)}"
    except OSError as e:
        where = f" ({STARTUP_FILE} not written: {e})"
    (pbar.write if pbar is not None else print)(clock.line() + where, file=sys.stderr)


def _write_error(run_dir: str, e: OSError, what: str, resume: bool = False, note: str = ""):
    """A one-line RunDirError for a failed write under `run_dir` (a full disk, a read-only
    directory), naming the fix."""
    from dscpp_jax.run_logging import RunDirError, os_error_fix
    fix = os_error_fix(e, run_dir, run_dir if resume else None)
    return RunDirError(f"could not {what} under {run_dir} ({e.strerror or e})"
                       + (f"; {note}" if note else "") + f". Fix: {fix}")


INBAND_LINE_EVERY = 10   # without a progress bar, in-band success is printed every this many iterations


def _inband_rate(m: dict) -> str:
    """In-band success over its window ("-" until an in-band episode finished)."""
    return f"{m['inband/success_rate']:.2f}" if m.get("inband/window", 0) > 0 else "-"


def _inband_text(m: dict) -> str:
    """" inband_success R (N episodes)" for the progress line when in-band evaluation is on."""
    if "inband/success_rate" not in m:
        return ""
    return f" inband_success {_inband_rate(m)} ({int(m['inband/episodes'])} episodes)"


def _schedule_done(cfg: Config, state) -> bool:
    """The run's schedule is over: total_env_steps reached, or total_episodes (when > 0)."""
    c = state.counters
    if int(c.env_steps) >= cfg.total_env_steps:
        return True
    return cfg.total_episodes > 0 and int(c.episodes) >= cfg.total_episodes


def _previous_wall(run_dir: str) -> float:
    from dscpp_jax.run_logging import read_metrics
    try:
        w = [x for x in read_metrics(run_dir).get("wall_clock", []) if x == x]
        return float(w[-1]) if w else 0.0
    except FileNotFoundError:
        return 0.0


def load_run(run_dir: str, step: Optional[int] = None):
    """(config, state) of a run directory's latest (or given) checkpoint."""
    import jax

    from dscpp_jax import checkpoint as ck
    from dscpp_jax import trainer as T
    from dscpp_jax import group_train
    if group_train.group_of(run_dir) is not None:   # a seed directory inside a seed group
        return group_train.load_seed(run_dir, step)
    if group_train.is_group_dir(run_dir):
        raise ValueError(f"{run_dir} is a seed group; name one of its seeds, e.g. "
                         f"{os.path.join(run_dir, 's%d' % group_train.read_group(run_dir)['seeds'][0])}")
    from dscpp_jax.run_logging import load_config
    cfg = load_config(run_dir)
    try:
        state = ck.restore_state(run_dir, T.init(jax.random.PRNGKey(cfg.seed), cfg), step)
    except ck.NoCheckpointError as e:
        raise ck.NoCheckpointError(f"run {run_dir} has no checkpoint to load ({e})") from None
    return cfg, state


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
    import jax

    from dscpp_jax.evaluate import evaluate
    starts = parse_starts(args.starts)   # a typo here fails before anything loads
    from dscpp_jax import group_train
    if group_train.is_group_dir(args.run):
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
        raise _write_error(args.run, e, f"write {name}.json") from None
    print(json.dumps({k: v for k, v in summary.items() if "option_success/" not in k
                      or v == v}, indent=2))
    if not args.no_plot:
        from dscpp_jax import plots
        path = os.path.join(args.run, f"{name}_trajectory.png")
        try:
            plots.plot_trajectory(cfg, res, path, title=f"{cfg.env} {cfg.algo} (iteration "
                                  f"{summary['iteration']})")
        except OSError as e:
            raise _write_error(args.run, e, f"write {name}_trajectory.png") from None
        print(f"wrote {out_json} and {path}")
    return 0


def _eval_record(summary: dict, counters, res, starts, explore: bool) -> dict:
    """An evaluation's JSON record: the summary, where the run stood (`counters` of one seed),
    per-start outcomes with `starts`, and whether it acted with exploration noise."""
    import numpy as np
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
    import jax
    import numpy as np

    from dscpp_jax import group_train
    from dscpp_jax import seed_group as SG
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
                from dscpp_jax import plots
                plots.plot_trajectory(cfg.override(seed=int(seed)), one,
                                      os.path.join(d, f"{name}_trajectory.png"),
                                      title=f"{cfg.env} {cfg.algo} seed {seed} (iteration "
                                            f"{summary['iteration']})")
        except OSError as e:
            raise _write_error(d, e, f"write {name}.json") from None
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
    from dscpp_jax import video
    out = out or os.path.join(run_dir, "videos")
    paths = video.render_run(cfg, state, out, episodes=episodes, starts=starts, seed=seed,
                             **options)
    for k, p in paths.items():
        print(f"{k}: {p}")
    return paths


def cmd_video(args) -> int:
    from dscpp_jax import video
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
        from dscpp_jax.run_logging import load_config
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
    from dscpp_jax import plots
    out = args.out or (os.path.join(args.runs[0], "plots") if len(args.runs) == 1 else "plots")
    try:
        paths = plots.plot_runs(args.runs, out, with_state=not args.curves_only,
                                trajectory=not args.regions_only)
    except OSError as e:
        if isinstance(e, ValueError):
            raise
        from dscpp_jax.run_logging import RunDirError, os_error_fix
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
    from dscpp_jax import compare
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
        from dscpp_jax.run_logging import wandb_missing_error
        missing = wandb_missing_error()
        if missing:
            raise ValueError(missing)
        wandb = {"project": args.wandb_project, "mode": args.wandb_mode}
    if args.video:   # bad video options fail now, not after training
        from dscpp_jax import video
        try:
            video.check_options(**_video_options(args))
        except video.VideoError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    if args.resume:
        from dscpp_jax.run_logging import load_config
        cfg = load_config(args.resume)
        cfg = cfg.override(**resume_changes(args, cfg))
        run_dir = args.resume
    else:
        cfg = config_from_args(args)
        run_dir = args.run_dir
    try:
        state, run_dir = train(cfg, run_dir, resume=bool(args.resume), time_budget=args.time_budget,
                               progress=not args.no_progress, wandb=wandb,
                               overwrite=args.overwrite)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        quiet_after_error()
        return 3
    if args.resume:
        from dscpp_jax.run_logging import read_config, write_config
        payload = read_config(run_dir)
        try:
            write_config(run_dir, cfg.to_dict(), {k: v for k, v in payload.items()
                                                  if k not in ("config", "versions",
                                                               "config_defaults")})
        except OSError as e:
            raise _write_error(run_dir, e, "update config.json") from None
    if not _schedule_done(cfg, state):   # the final evaluation belongs to the schedule's end
        print(f"run: {run_dir}\nstopped at iteration {int(state.counters.iteration)} "
              f"({int(state.counters.env_steps)} env steps, {int(state.counters.episodes)} "
              f"episodes) before the end of its schedule; continue with `train --resume "
              f"{run_dir}`, evaluate with `eval --run {run_dir}`")
        return 0
    from dscpp_jax.evaluate import evaluate
    ev, res = evaluate(state, num_episodes=cfg.eval_episodes)
    final = dict(ev, iteration=int(state.counters.iteration),
                 env_steps=int(state.counters.env_steps),
                 episodes_trained=int(state.counters.episodes), seed=cfg.seed)
    try:   # the same file a seed group writes for each seed, and `eval` for a checkpoint
        with open(os.path.join(run_dir, "eval.json"), "w") as f:
            json.dump(final, f, indent=2)
    except OSError as e:
        raise _write_error(run_dir, e, "write eval.json") from None
    if args.plot:
        from dscpp_jax import plots
        out = os.path.join(run_dir, "plots")
        it = int(state.counters.iteration)
        plots.plot_curves([run_dir], os.path.join(out, "curves.png"))
        plots.plot_trajectory(cfg, res, os.path.join(out, "trajectory.png"),
                              title=f"{cfg.env} {cfg.algo}, iteration {it}, "
                                    f"{int(state.counters.env_steps)} env steps")
        plots.plot_classifiers(cfg, state, os.path.join(out, "classifiers.png"))
    if args.video:
        from dscpp_jax import video
        try:
            write_videos(cfg, state, run_dir, episodes=args.video_episodes,
                         **_video_options(args))
        except video.VideoError as e:   # the run is saved; only its video is missing
            print(f"error: no video: {e}; render it later with: make video RUN={run_dir}",
                  file=sys.stderr)
    print(f"run: {run_dir}\nenv steps {int(state.counters.env_steps)}, episodes "
          f"{int(state.counters.episodes)}, eval success {ev['eval/success_rate']:.2f}, "
          f"options {int(ev['eval/num_options'])}")
    verdict = _chain_verdict(cfg, run_dir)
    if verdict:
        print(f"chain: {verdict} (python -m dscpp_jax.cli diagnose {run_dir})")
    return 0


def _chain_verdict(cfg, run_dir: str):
    """`diagnose`'s verdict for a finished run with a skill chain (None for flat learners or
    when the run left no eval.json)."""
    if not cfg.hierarchical or not os.path.isfile(os.path.join(run_dir, "eval.json")):
        return None
    try:
        return diagnose.diagnose_run(run_dir)["verdict"]
    except (ValueError, OSError):
        return None


# ------------------------------------------------------------------------------------------------
# Seed groups: `train --seeds 0-7` (dscpp_jax.seed_group, dscpp_jax.group_train)
# ------------------------------------------------------------------------------------------------
class _SeedGiven(argparse.Action):
    """--seed that remembers it was given (so that --seed with --seeds is an error)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.seed_given = True


def _resumes_group(args) -> bool:
    from dscpp_jax.group_train import is_group_dir
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
    from dscpp_jax import group_train
    from dscpp_jax import seed_group as SG
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
        if not group_train.is_group_dir(args.resume):
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
            progress=not args.no_progress, plot=args.plot, overwrite=args.overwrite)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        quiet_after_error()
        return 3
    import jax
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
    import numpy as np
    succ = np.array([s["eval/success_rate"] for s in summaries])
    print(f"group: {group_dir} ({len(seeds)} seeds on {jax.device_count()} devices)")
    for i, s in enumerate(seeds):
        verdict = _chain_verdict(cfg, group_train.seed_dir(group_dir, s))
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


def _saved_config(run_dir: str) -> Optional[dict]:
    """The config saved in a run's config.json or a group's group.json, read without touching
    JAX; None when there is none to read."""
    for name in ("config.json", "group.json"):
        try:
            with open(os.path.join(run_dir, name)) as f:
                return dict(json.load(f)["config"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return None


def _saved_config_of(args) -> Optional[dict]:
    """The saved config of the command's `--resume` / `--run` directory; None without one."""
    saved_dir = getattr(args, "resume", None) or getattr(args, "run", None)
    return _saved_config(saved_dir) if saved_dir else None


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
    from dscpp_jax.envs.ant_maze import warp_available
    return warp_available()


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
    import threading
    if not _FROM_COMMAND_LINE:
        return
    sys.unraisablehook = lambda unraisable: None
    threading.excepthook = lambda hook_args: None


_FROM_COMMAND_LINE = False
"""Set by `main()` run as the process's command (no argv given): only then does a start-up
record count the process's own start (interpreter, imports) as part of the command."""


def main(argv: Optional[list[str]] = None) -> int:
    global _FROM_COMMAND_LINE
    _FROM_COMMAND_LINE = argv is None
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
        from dscpp_jax.run_logging import os_error_fix
        where = getattr(e, "filename", None) or "the run directory"
        print(f"error: {e.strerror or e} ({where}). Fix: {os_error_fix(e, str(where))}",
              file=sys.stderr)
        quiet_after_error()
        return 2


if __name__ == "__main__":
    sys.exit(main())

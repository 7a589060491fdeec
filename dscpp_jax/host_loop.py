"""The host loop: what happens around the jitted `train_step` while a run trains, for a single run
and a seed group alike (a single run is a group of one).

    run_loop(cfgs, counters, hooks, ...)   the loop: Ctrl-C, the time budget, the schedule, the
                                           health check of each iteration, metrics rows, in-band
                                           evaluations, chain warnings, checkpoint cadence and
                                           the final checkpoint
    LoopHooks                              its side effects (step, evaluate, log, save, progress,
                                           start-up record), as Brax's train(progress_fn=...)
                                           keeps timing and logging outside the jitted code
    train(cfg, run_dir, ...)               one run: its hooks around `trainer.train_step`
                                           (`group_train.train_group` is the seed group's)

The loop works on arrays of one value per seed (shape (n,)); the jitted programs it drives never
see it, so the rows it writes, and the checkpoints, are those of the programs alone.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import sys
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils

from dscpp_jax import checkpoint as ck
from dscpp_jax import runtime
from dscpp_jax import trainer as T
from dscpp_jax.config import MEDIUM_MODEL_FREE_TD3, MODEL_BASED_ALGOS, Config, preset
from dscpp_jax.evaluate import evaluate
from dscpp_jax.options import TABLE_PREFIX
from dscpp_jax.run_dir import check_fresh, default_run_dir, lock_run_dir, previous_wall
from dscpp_jax.run_logging import (STARTUP_FILE, RunDirError, RunLogger, StartupClock,
                                   load_config, os_error_fix, process_age_s, write_config)


class TrainingDiverged(RuntimeError):
    """Learning produced NaN/inf; the message names the component."""


class Budget:
    """A wall-clock budget of `seconds` for a training command, counted from the start of the
    process (`count_process`, as the command line does) or from its creation. The loop asks
    `no_room()` before each iteration: true once the time left would not hold one more iteration
    (as long as the last one, not counting the first, which compiles) and the final checkpoint
    (as long as the last one written here). `None` seconds: no budget."""

    def __init__(self, seconds: Optional[float], count_process: bool = False):
        self.seconds = seconds
        age = process_age_s() if count_process else None
        self.start = time.time() - (age or 0.0)
        self.iterations = 0
        self.step_s = 0.0
        self.save_s = 0.0
        self.reached = False

    @property
    def deadline(self) -> float:
        return math.inf if self.seconds is None else self.start + self.seconds

    def iteration_took(self, seconds: float) -> None:
        self.iterations += 1
        if self.iterations > 1:   # the first iteration compiles: no guide to the next one
            self.step_s = seconds

    def save_took(self, seconds: float) -> None:
        self.save_s = max(self.save_s, seconds)

    def no_room(self, now: Optional[float] = None) -> bool:
        """Whether the loop must stop now to end within the budget (never before an iteration
        has run in this process)."""
        if self.seconds is None or self.iterations == 0:
            return False
        now = time.time() if now is None else now
        self.reached = now + self.step_s + self.save_s >= self.deadline
        return self.reached

    def reached_text(self) -> str:
        return (f"time budget of {self.seconds:.0f}s reached (counted from the start of the "
                f"process): saving a checkpoint and stopping")


def nonfinite_parts(metrics: dict) -> Optional[str]:
    """The parts of the learner whose values are no longer finite in one iteration's metrics
    (the ``finite/*`` flags and the TD3 and dynamics losses), named for a message; None when all
    are finite."""
    bad = [k.split("/", 1)[1] for k, v in metrics.items()
           if k.startswith("finite/") and float(v) < 0.5]
    for k in ("td3/critic_loss", "td3/actor_loss", "dynamics/loss"):
        if k in metrics and not math.isfinite(float(metrics[k])):
            bad.append(k)
    if not bad:
        return None
    names = {"td3": "the TD3 actor/critic parameters", "dynamics": "the dynamics model parameters",
             "classifiers": "the initiation classifiers (SVM coefficients)"}
    return ", ".join(names.get(b, b) for b in dict.fromkeys(bad))


def on_main_thread() -> bool:
    """Whether this is the main thread (only it can install a SIGINT handler)."""
    return threading.current_thread() is threading.main_thread()


def schedule_done(cfg: Config, env_steps: float, episodes: float) -> bool:
    """One seed's schedule is over: total_env_steps reached, or total_episodes (when > 0)."""
    if env_steps >= cfg.run.total_env_steps:
        return True
    return cfg.run.total_episodes > 0 and episodes >= cfg.run.total_episodes


def state_done(cfg: Config, state) -> bool:
    """`schedule_done` for a single run's TrainState."""
    c = state.counters
    return schedule_done(cfg, int(c.env_steps), int(c.episodes))


# ------------------------------------------------------------------------------------------------
# Chain health: the warnings a training run prints once each
# ------------------------------------------------------------------------------------------------
STALLED_LINK_EXECUTIONS = 1000
"""A link in gestation that failed this many executions without a success has stalled."""


def _metric(d: dict, key: str, default: float) -> float:
    try:
        return float(d.get(key, default))
    except (TypeError, ValueError):
        return default


def link_stalled(metrics: dict) -> bool:
    """The link in gestation has failed at least ``STALLED_LINK_EXECUTIONS`` executions without a
    success (``options/gestation_executions``, ``options/gestation_successes`` of one iteration's
    metrics or ``metrics.csv`` row)."""
    return (_metric(metrics, "options/gestation_executions", 0.0) >= STALLED_LINK_EXECUTIONS
            and _metric(metrics, "options/gestation_successes", 1.0) == 0)


def stuck_chain_warning(metrics: dict, cfg: Config, who: str = "") -> Optional[str]:
    """The warning for a chain that can no longer reach the start, or None: every row of the option
    table is in use (``options/capacity_hit``: a new option was needed and there was no room) and
    no option's initiation region holds the task start (``options/start_covered``). The original
    algorithm has no cap and would add an option; here no new link can be made, so success from
    the start stays near 0 unless a refit widens an existing region again
    (``experiments/results/README.md``, medium maze)."""
    if metrics.get("options/capacity_hit", 0) < 0.5 or metrics.get("options/start_covered", 1) > 0.5:
        return None
    return (f"warning: {who}the option table is full (max_options={cfg.chain.max_options}) and no "
            f"option's initiation region holds the task start any more; the chain cannot add the "
            f"link it needs, so success from the start will likely stay near 0. Restart with more "
            f"rows, e.g. --set max_options={cfg.chain.max_options + 8}.")


def stalled_link_warning(metrics: dict, cfg: Config, who: str = "") -> Optional[str]:
    """The warning for a chain link in gestation that has failed ``STALLED_LINK_EXECUTIONS`` or
    more executions without one success (``options/gestation_executions``,
    ``options/gestation_successes``), or None. Until it matures no new link is made, so the chain
    has stopped growing. Seen on the ant's medium maze, where such a link targeted an option in a
    dead end while that option's frontier stayed open (``experiments/results/README.md``, medium maze)."""
    if not link_stalled(metrics):
        return None
    n = metrics["options/gestation_executions"]
    parent = int(metrics.get("options/gestation_parent", -1))
    return (f"warning: {who}the option in gestation (it targets option {parent}) has failed "
            f"{int(n)} executions without one success, so the chain has stopped growing there. "
            f"Its target's region is likely out of reach from where its executions start; look at "
            f"the options' regions (`plot RUN_DIR --regions-only`). docs/cli.md, "
            f"\"diagnose\", says what to try.")


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


# ------------------------------------------------------------------------------------------------
# What a run prints about its preset
# ------------------------------------------------------------------------------------------------
def frontier_note(cfg: Config) -> str:
    """One line for a run whose skill chain uses the chain's frontier (beyond the paper; on in the
    ant preset for the medium and large mazes and for MB-DSC++, MF-DSC++ and DSC on four rooms),
    saying how to train the paper's rule instead; "" otherwise."""
    if not cfg.frontier_on:
        return ""
    return (f"{cfg.env}: the chain's frontier is on (beyond the paper: frontier_start_prob="
            f"{cfg.frontier.start_prob:g}, frontier_parent={str(cfg.frontier.parent).lower()}); "
            f"the paper's rule: --set frontier_start_prob=0 --set frontier_parent=false")


def medium_td3_note(cfg: Config) -> str:
    """One line for a model-free run on the ant medium maze with that maze's TD3 (HER `future`
    at 0.8 and twice the action penalty; beyond the paper, `config.MEDIUM_MODEL_FREE_TD3`),
    saying how to train the other mazes' TD3 instead; "" otherwise."""
    if cfg.env != "medium" or cfg.algo in MODEL_BASED_ALGOS or any(
            cfg.get(k) != v for k, v in MEDIUM_MODEL_FREE_TD3.items()):
        return ""

    def fmt(v):
        return f"{v:g}" if isinstance(v, float) else str(v)

    other = preset("fast", "four_rooms", cfg.algo)    # what the other ant mazes train with
    sets = ", ".join(f"{k}={fmt(v)}" for k, v in MEDIUM_MODEL_FREE_TD3.items())
    back = " ".join(f"--set {k}={fmt(other.get(k))}" for k in MEDIUM_MODEL_FREE_TD3)
    return (f"{cfg.env}: the model-free learners' TD3 of this maze (beyond the paper: {sets}); "
            f"the other ant mazes': {back}")


def notes_beyond_paper(cfg: Config) -> list:
    """The lines a train call prints about what its preset adds beyond the paper."""
    return [n for n in (frontier_note(cfg), medium_td3_note(cfg)) if n]


# ------------------------------------------------------------------------------------------------
# Pieces of the loop
# ------------------------------------------------------------------------------------------------
class Interrupt:
    """Ctrl-C as a request to stop after the current iteration, with a checkpoint; a second
    Ctrl-C aborts at once (KeyboardInterrupt). Installed on the main thread only, for the
    duration of a `with` block; `text` is what the first Ctrl-C prints."""

    def __init__(self, text: str):
        self.text = text
        self.requested = False
        self._old = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print("\n" + self.text, file=sys.stderr)

    def __enter__(self) -> "Interrupt":
        self._old = signal.signal(signal.SIGINT, self._handler) if on_main_thread() else None
        return self

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def write_error(run_dir: str, e: OSError, what: str, resume: bool = False,
                note: str = "") -> RunDirError:
    """A one-line RunDirError for a failed write under `run_dir` (a full disk, a read-only
    directory), naming the fix."""
    fix = os_error_fix(e, run_dir, run_dir if resume else None)
    return RunDirError(f"could not {what} under {run_dir} ({e.strerror or e})"
                       + (f"; {note}" if note else "") + f". Fix: {fix}")


def write_startup(clock: StartupClock, run_dir: str, say: Callable[[str], None],
                  **extra) -> None:
    """Record the command's start-up in run_dir/startup.jsonl and say it in one line."""
    try:
        clock.write(run_dir, **extra)
        where = f"; {os.path.join(run_dir, STARTUP_FILE)}"
    except OSError as e:
        where = f" ({STARTUP_FILE} not written: {e})"
    say(clock.line() + where)


def progress_bar(total: int, initial: int, desc: str):
    """A tqdm progress bar (tqdm is optional: None where it does not load)."""
    try:
        from tqdm import tqdm
        return tqdm(total=total, initial=initial, unit="step", dynamic_ncols=True, desc=desc)
    except Exception:  # noqa: BLE001
        return None


INBAND_LINE_EVERY = 10   # without a progress bar, in-band success is printed every this many iterations


def inband_rate(m: dict) -> str:
    """In-band success over its window ("-" until an in-band episode finished)."""
    return f"{m['inband/success_rate']:.2f}" if m.get("inband/window", 0) > 0 else "-"


def inband_text(m: dict) -> str:
    """" inband_success R (N episodes)" for the progress line when in-band evaluation is on."""
    if "inband/success_rate" not in m:
        return ""
    return f" inband_success {inband_rate(m)} ({int(m['inband/episodes'])} episodes)"


def value_range(x) -> str:
    """"lo-hi" of the finite values of `x` (one number when they agree, "-" when none)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not x.size:
        return "-"
    lo, hi = int(x.min()), int(x.max())
    return str(lo) if lo == hi else f"{lo}-{hi}"


def agree(flags: np.ndarray) -> np.ndarray:
    """Process 0's host decisions (stop, budget) in every process, so all stop together."""
    if jax.process_count() == 1:
        return flags
    return np.asarray(multihost_utils.broadcast_one_to_all(flags))


# ------------------------------------------------------------------------------------------------
# The loop
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Progress:
    """What the loop hands its progress hook after each iteration (values of shape (n,), one per
    seed): the loop's iteration, the step's metrics, each seed's row (None for a seed that was
    done), whether an in-band evaluation ran, the latest evaluation success of each seed, and
    the seconds the step took."""
    iteration: int
    metrics: Dict[str, np.ndarray]
    rows: List[Optional[dict]]
    active: np.ndarray
    env_steps: np.ndarray
    episodes: np.ndarray
    evaluated: bool
    last_eval: np.ndarray
    step_s: float


@dataclasses.dataclass
class LoopHooks:
    """The side effects of the host loop, each called at its point:

    step(active) -> (metrics, counters)   one iteration of the active seeds: metrics {name: (n,)}
                                          and (env_steps, episodes, iteration), each (n,)
    evaluate() -> [summary per seed]      an in-band evaluation of the current state
    log(i, row)                           seed i's metrics row
    save(iteration, wait)                 a checkpoint of the current state
    save_previous(iteration)              a checkpoint of the state before the last step
    latest_checkpoint() -> step or None
    diverged(bad, iteration) -> error     {seed index: parts} of a non-finite step
    progress(Progress)                    after each iteration (bar, lines)
    say(text)                             a line to stderr that does not break a progress bar
    startup(iteration)                    after the first iteration of this process
    """
    step: Callable
    evaluate: Callable
    log: Callable
    save: Callable
    save_previous: Callable
    latest_checkpoint: Callable
    diverged: Callable
    progress: Callable
    say: Callable
    startup: Callable


@dataclasses.dataclass
class LoopEnd:
    """Where the loop stopped: its iteration, each seed's counters and latest evaluation, and
    whether Ctrl-C stopped it."""
    iteration: int
    env_steps: np.ndarray
    episodes: np.ndarray
    last_eval: np.ndarray
    interrupted: bool


def flush_pending(pending: Dict[int, dict], ev, log: Callable, last_eval) -> None:
    """Log the rows left waiting for an evaluation, with seed i's numbers from `ev[i]` (none
    where `ev` is None)."""
    for i, row in sorted(pending.items()):
        if ev is not None:
            row.update(ev[i])
            last_eval[i] = ev[i]["eval/success_rate"]
        log(i, row)
    pending.clear()


def run_loop(cfgs: Sequence[Config], counters: tuple, hooks: LoopHooks, *, budget: Budget,
             interrupt: Interrupt, walls: Sequence[float], who: Callable[[int, int], str],
             saved_text: Callable[[int], str], max_iterations: Optional[int] = None,
             pending: Optional[Dict[int, dict]] = None, group_rate: bool = False,
             t_start: Optional[float] = None) -> LoopEnd:
    """Train until every seed's schedule is over, Ctrl-C (`interrupt`), the time budget or
    `max_iterations` iterations of this call; then save a checkpoint unless the last one holds
    the final state. `cfgs[i]`, `walls[i]`: seed i's config and the wall-clock its earlier
    rows reached; `counters`: (env_steps, episodes, iteration) arrays at the start.

    Seed i's row of an iteration holds its counters, the wall-clock, the step's time and its
    metrics; at the evaluation cadence (`eval_every`, and the end of a seed's schedule) also an
    in-band evaluation. With `pending` (a dict), a seed that ends its schedule between
    evaluations is not evaluated on its own: its last row waits there for the next evaluation or
    the caller's final one (a seed group); without it, it is evaluated at once. `group_rate`
    adds the column time/group_env_steps_per_s. `who(i, it)` starts a chain warning's text;
    `saved_text(it)` is the line after a checkpoint on Ctrl-C. The rows' wall-clock counts from
    `t_start` (default: now)."""
    n = len(cfgs)
    cfg = cfgs[0]
    env_steps, episodes, iters = (np.asarray(c) for c in counters)
    env_steps = env_steps.astype(float)
    episodes = episodes.astype(float)
    iters = iters.astype(int)
    start_iter = int(iters.max())
    loop_it = saved_iter = start_iter
    last_eval = np.full((n,), np.nan)
    warned = [set() for _ in range(n)]   # chain warnings printed, per seed (each kind once)
    t_start = time.time() if t_start is None else t_start
    first = True
    while True:
        active = np.array([not schedule_done(c, e, p) for c, e, p in zip(cfgs, env_steps, episodes)])
        if not active.any():
            break
        if max_iterations is not None and loop_it - start_iter >= max_iterations:
            break
        if agree(np.array([budget.no_room()]))[0]:
            print(budget.reached_text(), file=sys.stderr)
            break
        t0 = time.time()
        m, (step_env, step_eps, step_its) = hooks.step(active)
        dt = time.time() - t0
        if first:
            first = False
            hooks.startup(loop_it)
        bad = {i: b for i in range(n) if active[i]
               for b in [nonfinite_parts({k: v[i] for k, v in m.items()})] if b}
        if bad:
            if saved_iter != loop_it or hooks.latest_checkpoint() is None:
                hooks.save_previous(loop_it)
            raise hooks.diverged(bad, loop_it)
        loop_it += 1
        env_steps = np.where(active, step_env, env_steps)
        episodes = np.where(active, step_eps, episodes)
        finished = active & np.array([schedule_done(c, e, p) for c, e, p in
                                      zip(cfgs, env_steps, episodes)])
        iters = np.where(active, step_its, iters).astype(int)
        periodic = active & ((iters % cfg.eval.every == 0) if cfg.eval.every
                             else np.zeros((n,), bool))
        due = periodic | (finished & bool(cfg.eval.every))
        # A seed that just finished is frozen, so its evaluation gives the same numbers at any
        # later point (the key comes from its iteration): with `pending`, evaluate now only when
        # a periodic evaluation is due anyway, else leave its last row waiting for the next
        # evaluation of the group or the final one, instead of one evaluation per finishing seed.
        ev = None
        if periodic.any() or (pending is None and due.any()):
            ev = hooks.evaluate()
            if pending:
                flush_pending(pending, ev, hooks.log, last_eval)
        rate = cfg.steps_per_iteration_total / max(dt, 1e-9)
        rows: List[Optional[dict]] = [None] * n
        for i in range(n):
            if not active[i]:
                continue
            row = {"iteration": int(iters[i]), "env_steps": float(m["counters/env_steps"][i]),
                   "episodes": float(m["counters/episodes"][i]),
                   "wall_clock": walls[i] + time.time() - t_start, "time/iteration_s": dt,
                   "time/env_steps_per_s": rate}
            if group_rate:
                row["time/group_env_steps_per_s"] = rate * int(active.sum())
            row.update({k: (np.asarray(v[i]) if k.startswith(TABLE_PREFIX) else float(v[i]))
                        for k, v in m.items() if not k.startswith("counters/")})
            rows[i] = row
            if due[i] and ev is None:
                pending[i] = row
                continue
            if due[i]:
                row.update(ev[i])
                last_eval[i] = ev[i]["eval/success_rate"]
            hooks.log(i, row)
            for kind, msg in chain_warnings(row, cfgs[i], who(i, int(iters[i]))):
                if kind not in warned[i]:
                    warned[i].add(kind)
                    hooks.say(msg)
        hooks.progress(Progress(iteration=loop_it, metrics=m, rows=rows, active=active,
                                env_steps=env_steps, episodes=episodes, evaluated=ev is not None,
                                last_eval=last_eval, step_s=dt))
        if cfg.run.checkpoint_every and loop_it % cfg.run.checkpoint_every == 0:
            hooks.save(loop_it, False)   # written while the next iterations run
            saved_iter = loop_it
        budget.iteration_took(time.time() - t0)
        if agree(np.array([interrupt.requested]))[0]:
            break
    if loop_it != saved_iter or hooks.latest_checkpoint() is None:
        t0 = time.time()
        hooks.save(loop_it, True)
        budget.save_took(time.time() - t0)
    if interrupt.requested:
        print(saved_text(loop_it), file=sys.stderr)
    return LoopEnd(iteration=loop_it, env_steps=env_steps, episodes=episodes, last_eval=last_eval,
                   interrupted=interrupt.requested)


# ------------------------------------------------------------------------------------------------
# One run: a group of one around trainer.train_step
# ------------------------------------------------------------------------------------------------
class RunProgress:
    """The progress of one run: a tqdm bar (with `bar`), else one line per evaluation and one
    per `INBAND_LINE_EVERY` iterations with in-band evaluation."""

    def __init__(self, cfg: Config, env_steps: int, bar: bool):
        self.pbar = progress_bar(cfg.run.total_env_steps, env_steps,
                                 f"{cfg.env}/{cfg.algo}") if bar else None

    def say(self, text: str) -> None:
        (self.pbar.write if self.pbar is not None else print)(text, file=sys.stderr)

    def __call__(self, p: Progress) -> None:
        row = p.rows[0]
        m = {k: float(v[0]) for k, v in p.metrics.items() if not k.startswith(TABLE_PREFIX)}
        it, last_eval = row["iteration"], float(p.last_eval[0])
        if self.pbar is None and p.evaluated:
            print(f"[{row['wall_clock']:7.0f}s] it {it} env_steps {int(row['env_steps'])} "
                  f"episodes {int(row['episodes'])} eval_success {last_eval:.2f} "
                  f"steps_to_goal {row['eval/steps_to_goal']:.0f}{inband_text(m)} options "
                  f"{int(m.get('options/num_options', 1))} train_success "
                  f"{m.get('train/episode_success', float('nan')):.2f} "
                  f"steps/s {row['time/env_steps_per_s']:.0f}", flush=True)
        elif self.pbar is None and "inband/success_rate" in m and it % INBAND_LINE_EVERY == 0:
            print(f"[{row['wall_clock']:7.0f}s] it {it} env_steps {int(row['env_steps'])} "
                  f"episodes {int(row['episodes'])}{inband_text(m)} options "
                  f"{int(m.get('options/num_options', 1))} "
                  f"steps/s {row['time/env_steps_per_s']:.0f}", flush=True)
        if self.pbar is not None:
            self.pbar.update(int(m["counters/env_steps"]) - self.pbar.n)
            inband = {"inband_success": inband_rate(m)} if "inband/success_rate" in m else {}
            self.pbar.set_postfix(episodes=int(m["counters/episodes"]),
                                  eval_success=f"{last_eval:.2f}", **inband,
                                  options=int(m.get("options/num_options", 1)),
                                  steps_per_s=f"{row['time/env_steps_per_s']:.0f}", refresh=False)

    def close(self) -> None:
        if self.pbar is not None:
            self.pbar.close()


def train(cfg: Optional[Config] = None, run_dir: Optional[str] = None, resume: bool = False,
          time_budget: Optional[float] = None, progress: bool = True,
          max_iterations: Optional[int] = None, initial_state=None,
          wandb: Optional[dict] = None, overwrite: bool = False, count_process: bool = False):
    """Train (or resume) a run; returns (state, run_dir). Saves checkpoints and metrics.csv.

    `initial_state` (optional) replaces `init(PRNGKey(seed), cfg)` for a fresh run. `wandb`
    (optional): `{"project": ..., "mode": ...}` also logs to Weights & Biases.
    The run directory is locked for this process (`run_dir.lock_run_dir`); a fresh run refuses a
    directory that holds an earlier run unless `overwrite`, which clears it first.
    `time_budget` (seconds) counts from the start of the process with `count_process` (as the
    command line does), else from this call: the loop stops, with a checkpoint, before an
    iteration that would end past it. The final evaluation belongs to the end of the schedule
    (the command line's `train`, or `eval`). A directory that cannot be read or written raises a
    ValueError (`RunDirError`, `CheckpointError`) that names the fix; what was saved before
    stays as it was."""
    clock = StartupClock(count_process=count_process)
    budget = Budget(time_budget, count_process=count_process)
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
    if runtime.is_ant(cfg):
        print(runtime.physics_line(cfg), file=sys.stderr)
    for note in notes_beyond_paper(cfg):
        print(note, file=sys.stderr)
    try:
        lock_run_dir(run_dir)
        if not resume:
            check_fresh(run_dir, overwrite)
    except RunDirError:
        raise
    except OSError as e:
        raise write_error(run_dir, e, "create the run directory") from None
    for line in runtime.cpu_warnings(cfg):
        print(line, file=sys.stderr)

    key = jax.random.PRNGKey(cfg.run.seed)
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
            raise write_error(run_dir, e, "write config.json") from None
    try:
        logger = RunLogger(run_dir, resume_iteration=start_iter,
                           wandb=None if wandb is None else {**wandb, "config": cfg.flat()})
    except OSError as e:
        raise write_error(run_dir, e, "write metrics.csv") from None
    ckpt = ck.Checkpointer(run_dir, keep=cfg.run.keep_checkpoints)
    box = {"state": state, "prev": state}   # the state, and the one before the last step
    interrupt = Interrupt("interrupt: finishing this iteration, saving a checkpoint, then exiting "
                          "(Ctrl-C again to abort without saving)")
    show = None

    def step(active):
        box["prev"] = box["state"]
        box["state"], m = T.train_step(box["state"])
        m = {k: np.asarray(v)[None] for k, v in jax.device_get(m).items()}
        c = box["state"].counters
        return m, tuple(np.array([int(x)]) for x in (c.env_steps, c.episodes, c.iteration))

    def startup(loop_it):
        clock.mark("first iteration")
        write_startup(clock, run_dir, show.say, iteration=int(box["state"].counters.iteration),
                      resumed_at_iteration=start_iter, physics=cfg.task.physics,
                      device=str(jax.devices()[0].device_kind))

    def diverged(bad, it):
        return TrainingDiverged(
            f"learning diverged at iteration {it + 1}: non-finite values in {bad[0]}. The last "
            f"finite state was saved (iteration {it}) under {run_dir}/checkpoints. Lower the "
            f"learning rates (td3_lr, dyn_lr) or the updates per step and resume or restart.")

    try:
        with interrupt:
            show = RunProgress(cfg, int(state.counters.env_steps), progress)
            hooks = LoopHooks(
                step=step, evaluate=lambda: [evaluate(box["state"])[0]],
                log=lambda i, row: logger.log(row),
                save=lambda it, wait: ckpt.save(it, box["state"], wait=wait),
                save_previous=lambda it: ckpt.save(it, box["prev"]),
                latest_checkpoint=ckpt.latest_step, diverged=diverged, progress=show,
                say=show.say, startup=startup)
            clock.mark("set-up")
            c = state.counters
            run_loop([cfg], tuple(np.array([int(x)]) for x in (c.env_steps, c.episodes,
                                                                c.iteration)),
                     hooks, budget=budget, interrupt=interrupt, walls=[previous_wall(run_dir)],
                     who=lambda i, it: f"iteration {it}: ",
                     saved_text=lambda it: f"saved a checkpoint at iteration {it}; continue with "
                                           f"--resume {run_dir}",
                     max_iterations=max_iterations)
    except OSError as e:
        if isinstance(e, ck.CheckpointError):
            raise
        last = ckpt.latest_step()
        raise write_error(run_dir, e, "write the run's logs (metrics.csv)", resume=True,
                          note=f"the last checkpoint (iteration {last}) is intact"
                          if last is not None else "") from None
    finally:
        if show is not None:
            show.close()
        ending_error = sys.exc_info()[0]   # set while an exception ends the run
        for close in (logger.close, ckpt.close):
            try:
                close()
            except Exception:  # noqa: BLE001 - never hide the error that ended the run
                if ending_error is None:
                    raise
    return box["state"], run_dir


def final_evaluation(state, run_dir: str):
    """The evaluation at the end of a run's schedule (`eval_episodes` episodes from the task
    start), written to run_dir/eval.json with where the run stood, as a seed group writes it
    for each seed and `eval` for a checkpoint. Returns (summary, EvalResult)."""
    cfg = state.config
    ev, res = evaluate(state, num_episodes=cfg.eval.episodes)
    c = state.counters
    final = dict(ev, iteration=int(c.iteration), env_steps=int(c.env_steps),
                 episodes_trained=int(c.episodes), seed=cfg.run.seed)
    try:
        with open(os.path.join(run_dir, "eval.json"), "w") as f:
            json.dump(final, f, indent=2)
    except OSError as e:
        raise write_error(run_dir, e, "write eval.json") from None
    return ev, res

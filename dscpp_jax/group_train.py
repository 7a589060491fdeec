"""Host-side driver of seed groups (`train --seeds 0-7`): one jitted program trains every seed;
each seed keeps an ordinary run directory inside the group directory.

    runs/<env>-<algo>-g0-7-<time>/
      group.json          seeds, config, command, devices, processes, library versions
      checkpoints/<it>/   one orbax checkpoint of the whole group state
      plots/curves.png    with --plot: curves over the seeds (mean +- s.e.)
      s0/ s1/ ...         one run directory per seed: config.json (its own seed), metrics.csv,
                          tb/, eval.json, plots/ (with --plot); no checkpoints of its own

`eval --run GROUP/s3` and `plot GROUP/s0 GROUP/s1` work on a seed directory: `load_run` sees that
it belongs to a group and restores the group checkpoint, then takes that seed out of it
(`load_seed`). A seed of a group whose learning diverges stops the whole group (one program, one
checkpoint): the last finite group state is saved and the error names the seed(s).
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from typing import Callable, Dict, Optional, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils

from dscpp_jax import host_loop as HL
from dscpp_jax import runtime
from dscpp_jax import seed_group as SG
from dscpp_jax import trainer as T
from dscpp_jax.config import Config
from dscpp_jax.host_loop import Budget, Interrupt, LoopHooks, Progress, TrainingDiverged
from dscpp_jax.run_dir import (GROUP_FILE, check_fresh, group_of, is_group_dir,  # noqa: F401
                               load_group, load_seed, lock_run_dir, previous_wall, read_group,
                               seed_dir, seed_dirs)
from dscpp_jax.run_logging import (RunLogger, StartupClock, atomic_write, library_versions,
                                   read_config, write_config)

__all__ = ["GROUP_FILE", "GroupTooLarge", "STATE_COPIES", "available_memory",
           "check_group_memory", "default_group_dir", "group_of", "is_group_dir", "load_group",
           "load_seed", "read_group", "resume_config", "seed_dir", "seed_dirs", "state_bytes",
           "train_group", "update_configs", "TrainingDiverged"]


def default_group_dir(cfg: Config, seeds: Sequence[int], root: str = "runs",
                      stamp: Optional[str] = None) -> str:
    """runs/<env>-<algo>-g<seeds>-<time>: where a fresh group goes without --run-dir."""
    stamp = stamp or time.strftime("%Y%m%d-%H%M%S")
    return os.path.join(root, f"{cfg.env}-{cfg.algo}-g{SG.format_seeds(seeds)}-{stamp}")


def _shared_stamp() -> str:
    """The same time stamp in every process (process 0's)."""
    t = int(time.time())
    if jax.process_count() > 1:
        t = int(multihost_utils.broadcast_one_to_all(np.int64(t)))
    return time.strftime("%Y%m%d-%H%M%S", time.localtime(t))


def _write_group_json(group_dir: str, cfg: Config, seeds, mesh, extra=None) -> None:
    payload = {"seeds": list(seeds), "config": cfg.override(seed=seeds[0]).to_dict(), "command": " ".join(sys.argv),
               "devices": [str(d) for d in jax.devices()], "mesh": {"seeds": int(mesh.size)},
               "process_count": jax.process_count(), "versions": library_versions()}
    payload.update(extra or {})
    try:
        atomic_write(os.path.join(group_dir, GROUP_FILE),
                     json.dumps(payload, indent=2, sort_keys=True))
    except OSError as e:
        raise HL.write_error(group_dir, e, f"write {GROUP_FILE}") from None


class GroupTooLarge(ValueError):
    """A seed group whose state would not fit in the memory of its devices or host."""


STATE_COPIES = 2
"""Group states a device holds at once while training: the state and the next one (the loop
keeps the previous state until the step's metrics are checked, to save it if they are not
finite)."""


def state_bytes(tree) -> int:
    """Bytes of the arrays of a (possibly abstract) pytree."""
    total = 0
    for x in jax.tree_util.tree_leaves(tree):
        try:
            itemsize = np.dtype(x.dtype).itemsize
        except TypeError:   # a typed PRNG key: its raw key data
            itemsize = 8
        total += int(np.prod(x.shape, dtype=np.int64)) * itemsize
    return total


def available_memory(devices) -> tuple:
    """(free bytes on each device, or None where the device does not say; free host memory in
    bytes, or None where unknown): a device's own pool (accelerators), the host's
    MemAvailable from /proc/meminfo."""
    per_device = []
    for d in devices:
        try:
            stats = d.memory_stats() or {}
        except Exception:  # noqa: BLE001 - back ends without memory statistics
            stats = {}
        limit = stats.get("bytes_limit")
        per_device.append(None if limit is None else int(limit) - int(stats.get("bytes_in_use", 0)))
    host = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    host = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return per_device, host


def check_group_memory(cfg: Config, n: int, mesh) -> dict:
    """Refuse (GroupTooLarge) a group of `n` seeds whose states would not fit: the shapes of the
    group state (`seed_group.group_shapes`, nothing allocated) against the free memory of the
    mesh's devices (`STATE_COPIES` states each) and of the host (where the devices are the host's
    CPU, or for the copy a checkpoint takes). Returns the numbers it compared."""
    _, one, like = SG.group_shapes(cfg, n)
    seed_b = state_bytes(one)
    total_b = state_bytes(like)
    devices = [d for d in mesh.devices.flat]
    local = [d for d in devices if d.process_index == jax.process_index()]
    per_dev_seeds = -(-n // max(1, len(devices)))
    shared_b = max(0, total_b - n * seed_b)   # buffers shared by every seed (MuJoCo Warp)
    dev_need = STATE_COPIES * (per_dev_seeds * seed_b + shared_b)
    free_dev, free_host = available_memory(local[:1])
    on_cpu = local[0].platform == "cpu"
    host_need = (STATE_COPIES if on_cpu else 1) * total_b * len(local) // max(1, len(devices))
    numbers = {"seed_bytes": seed_b, "device_need": dev_need, "device_free": free_dev[0],
               "host_need": host_need, "host_free": free_host}

    def gib(b):
        return f"{b / 2**30:.2f} GiB"
    fit = None
    if not on_cpu and free_dev[0] is not None and dev_need > free_dev[0]:
        fit = max(0, (free_dev[0] // STATE_COPIES - shared_b) // max(1, seed_b)) * len(devices)
        where = (f"{gib(dev_need)} on each of {len(devices)} {local[0].platform.upper()} "
                 f"device(s) ({STATE_COPIES} copies of {per_dev_seeds} seed states), but "
                 f"{gib(free_dev[0])} are free there")
    elif free_host is not None and host_need > free_host:
        copies = STATE_COPIES if on_cpu else 1
        fit = max(0, free_host // copies // max(1, seed_b)) * len(devices) // max(1, len(local))
        where = f"{gib(host_need)} of host memory, but {gib(free_host)} are available"
    if fit is not None:
        raise GroupTooLarge(
            f"a group of {n} seeds does not fit: one seed's state is {seed_b / 2**20:.1f} MiB "
            f"(replay_capacity={cfg.td3.replay_capacity}, model_capacity={cfg.dynamics.capacity}, "
            f"num_envs={cfg.run.num_envs}), so the group needs about {where}. Train at most {fit} "
            f"seeds at once, or lower replay_capacity / model_capacity. Nothing was written")
    return numbers


class GroupProgress:
    """The progress of a seed group: a tqdm bar over every seed's steps (with `bar`, on process
    0), else one line per evaluation and one per `host_loop.INBAND_LINE_EVERY` iterations with
    in-band evaluation, each with the spread over the seeds."""

    def __init__(self, cfg: Config, n: int, env_steps: np.ndarray, bar: bool, lead: bool,
                 t_start: float):
        self.cfg, self.lead, self.t_start = cfg, lead, t_start
        self.pbar = HL.progress_bar(cfg.run.total_env_steps * n, int(env_steps.sum()),
                                    f"{cfg.env}/{cfg.algo} x{n} seeds") if bar and lead else None
        self.inband = np.full((n,), np.nan)     # in-band success per seed (NaN: none finished yet)
        self.options = np.full((n,), np.nan)

    def say(self, text: str) -> None:
        if self.lead:
            (self.pbar.write if self.pbar is not None else print)(text, file=sys.stderr)

    def __call__(self, p: Progress) -> None:
        m, active, last_eval = p.metrics, p.active, p.last_eval
        if "options/num_options" in m:
            self.options = np.where(active, m["options/num_options"], self.options)
        if "inband/success_rate" in m:
            seen = active & (m["inband/window"] > 0)
            self.inband = np.where(seen, m["inband/success_rate"],
                                   np.where(active, np.nan, self.inband))
        rate = self.cfg.steps_per_iteration_total / max(p.step_s, 1e-9) * int(active.sum())
        ib = {} if not np.isfinite(self.inband).any() else {
            "inband_mean": f"{np.nanmean(self.inband):.2f}"}
        options = HL.value_range(self.options)
        if self.lead and self.pbar is not None:
            self.pbar.update(int(p.env_steps.sum()) - self.pbar.n)
            seen_eval = np.isfinite(last_eval).any()
            self.pbar.set_postfix(
                eval_mean=f"{np.nanmean(last_eval):.2f}" if seen_eval else "nan",
                eval_min=f"{np.nanmin(last_eval):.2f}" if seen_eval else "nan",
                **ib, options=options, steps_per_s=f"{rate:.0f}", refresh=False)
        elif self.lead and (p.evaluated or (ib and p.iteration % HL.INBAND_LINE_EVERY == 0)):
            ib_text = f" inband_success mean {ib['inband_mean']}" if ib else ""
            ev_text = (f"eval_success mean {np.nanmean(last_eval):.2f} min "
                       f"{np.nanmin(last_eval):.2f}" if np.isfinite(last_eval).any()
                       else "eval_success -")
            print(f"[{time.time() - self.t_start:7.0f}s] it {p.iteration} env_steps/seed "
                  f"{int(p.env_steps.max())} episodes/seed {HL.value_range(p.episodes)} "
                  f"{ev_text}{ib_text} options {options} steps/s (all seeds) {rate:.0f}",
                  flush=True)

    def close(self) -> None:
        if self.pbar is not None:
            self.pbar.close()


def train_group(cfg: Config, seeds: Sequence[int], group_dir: Optional[str] = None,
                resume: bool = False, time_budget: Optional[float] = None, progress: bool = True,
                max_iterations: Optional[int] = None, mesh=None,
                plot: Optional[Callable] = None, overwrite: bool = False,
                count_process: bool = False):
    """Train (or resume) a seed group; returns (group state, group_dir, per-seed eval summaries).

    `cfg.run.seed` is ignored: seed i of the group uses seeds[i]. Stops when every seed's schedule is
    over (a seed that is done earlier is frozen where its separate run would have stopped), on
    Ctrl-C, at the time budget or at `max_iterations` group iterations. The final evaluation
    (eval.json of each seed; the summaries) belongs to the end of the schedule: a group that stops
    before every seed is done returns None for the summaries. `plot` (optional), e.g.
    `plots.plot_group`, is called as plot(group_dir, cfgs, seed_dirs, host_states, results) on
    process 0 after the final evaluation. The group directory is locked for this process; a
    fresh group refuses a directory that holds an earlier run unless `overwrite`, and one too
    large for the devices' memory is refused before anything is allocated
    (`check_group_memory`). `time_budget` counts from the start of the process with
    `count_process` (as the command line does), else from this call."""
    clock = StartupClock(count_process=count_process)
    budget = Budget(time_budget, count_process=count_process)
    seeds = tuple(int(s) for s in seeds)
    n = len(seeds)
    mesh = SG.seed_mesh() if mesh is None else mesh
    SG.check_group_size(n, mesh)
    cfg = cfg.validate()
    lead = jax.process_index() == 0
    if group_dir is None:
        group_dir = default_group_dir(cfg, seeds, stamp=_shared_stamp())
    if resume and not is_group_dir(group_dir):
        raise ValueError(f"--resume needs an existing group directory (with {GROUP_FILE}), got "
                         f"{group_dir!r}")
    check_group_memory(cfg, n, mesh)   # before anything is allocated or written
    cfgs = [cfg.override(seed=s) for s in seeds]
    dirs = [seed_dir(group_dir, s) for s in seeds]
    if lead:
        lock_run_dir(group_dir)
        if not resume:
            check_fresh(group_dir, overwrite)
        for d in dirs:
            os.makedirs(d, exist_ok=True)
    for line in runtime.cpu_warnings(cfg):
        print(line, file=sys.stderr)

    clock.mark("set-up")
    box = {"states": SG.init_group(seeds, cfg, mesh)}
    jax.block_until_ready(box["states"])
    clock.mark("env build and init")
    ckpt = SG.GroupCheckpointer(group_dir, keep=cfg.run.keep_checkpoints)
    restored = resume and ckpt.latest_step() is not None
    if restored:
        box["states"] = ckpt.restore(box["states"], mesh)
        clock.mark("restore")
    c = SG.to_host(box["states"].counters)
    counters = (np.asarray(c.env_steps, float), np.asarray(c.episodes, float),
                np.asarray(c.iteration, int))
    start_iter = int(counters[2].max())
    if restored:
        print(f"resumed group {group_dir} at iteration {start_iter} (seeds {list(seeds)})",
              file=sys.stderr)
    elif lead:
        env_cfg = dataclasses.asdict(T.make_env(cfg).config)
        _write_group_json(group_dir, cfg, seeds, mesh, {"env": env_cfg})
        for i, (d, c_) in enumerate(zip(dirs, cfgs)):
            try:
                write_config(d, c_.to_dict(), {"command": " ".join(sys.argv), "env": env_cfg,
                                               "group": os.path.abspath(group_dir),
                                               "group_index": i})
            except OSError as e:
                raise HL.write_error(d, e, "write config.json") from None
    loggers = ([RunLogger(d, resume_iteration=int(it)) for d, it in zip(dirs, counters[2])]
               if lead else [])
    walls = [previous_wall(d) for d in dirs] if lead else [0.0] * n
    interrupt = Interrupt("interrupt: finishing this iteration, saving a checkpoint of the group, "
                          "then exiting (Ctrl-C again to abort without saving)")
    pending: Dict[int, dict] = {}   # seed index -> its last row, waiting for an evaluation
    show = None

    def step(active):
        box["prev"] = box["states"]
        box["states"], m = SG.train_step_group(box["states"], active, mesh)
        m = {k: np.asarray(v, float) for k, v in SG.to_host(m).items()}
        return m, (m["counters/env_steps"], m["counters/episodes"], m["counters/iteration"])

    def startup(group_it):
        clock.mark("first iteration")
        if lead:
            HL.write_startup(clock, group_dir, show.say, group_iteration=group_it + 1,
                             resumed_at_iteration=start_iter, seeds=list(seeds),
                             physics=T.resolve_physics(cfg).task.physics,
                             device=str(jax.devices()[0].device_kind))

    def diverged(bad, group_it):
        which = "; ".join(f"seed {seeds[i]}: {b}" for i, b in bad.items())
        return TrainingDiverged(
            f"learning diverged at iteration {group_it + 1} ({which}); the whole group "
            f"stopped. The last finite group state was saved (iteration {group_it}) under "
            f"{group_dir}/checkpoints. Lower the learning rates (td3_lr, dyn_lr) or the "
            f"updates per step, or start a group without seed(s) {sorted(seeds[i] for i in bad)}.")

    def log(i, row):
        if loggers:
            loggers[i].log(row)

    summaries = res = None
    try:
        with interrupt:
            t_start = time.time()
            show = GroupProgress(cfg, n, counters[0], progress, lead, t_start)
            # Warp's kernels build in a thread while XLA compiles the group step ahead of time
            # (after `init_group`; see `trainer.prewarm_physics`)
            clock.mark("set-up")
            prewarm = T.prewarm_physics(cfg.override(group_size=n))
            if prewarm is not None:
                fn, placed, all_active = SG.group_step_program(box["states"], mesh)
                fn.lower(placed, all_active).compile()
                clock.mark("XLA compile ahead (group step)")
                prewarm.join()
                clock.mark("MuJoCo Warp kernels left")
            hooks = LoopHooks(
                step=step,
                evaluate=lambda: SG.evaluate_group(box["states"], mesh=mesh)[0], log=log,
                save=lambda it, wait: ckpt.save(it, box["states"], wait=wait),
                save_previous=lambda it: ckpt.save(it, box["prev"]),
                latest_checkpoint=ckpt.latest_step, diverged=diverged, progress=show,
                say=show.say, startup=startup)
            end = HL.run_loop(
                cfgs, counters, hooks, budget=budget, interrupt=interrupt, walls=walls,
                who=lambda i, it: f"seed {seeds[i]}, iteration {it}: ",
                saved_text=lambda it: f"saved a checkpoint of the group at iteration {it}; "
                                      f"continue with --resume {group_dir}",
                max_iterations=max_iterations, pending=pending, group_rate=True,
                t_start=t_start)
            if all(HL.schedule_done(c_, e, p) for c_, e, p in
                   zip(cfgs, end.env_steps, end.episodes)):
                summaries, res = SG.evaluate_group(box["states"], num_episodes=cfg.eval.episodes,
                                                   mesh=mesh)
                HL.flush_pending(pending, summaries, log, end.last_eval)
    finally:
        HL.flush_pending(pending, None, log, np.full((n,), np.nan))   # on an error: no evaluation
        if show is not None:
            show.close()
        for lg in loggers:
            lg.close()
        ckpt.close()

    states = box["states"]
    c = SG.to_host(states.counters)               # collectives: every process takes part
    if summaries is None:
        return states, group_dir, None
    host = SG.to_host(states) if plot else None
    if lead:
        for i, d in enumerate(dirs):
            out = dict(summaries[i], iteration=int(c.iteration[i]), env_steps=int(c.env_steps[i]),
                       episodes_trained=int(c.episodes[i]), seed=seeds[i])
            try:
                with open(os.path.join(d, "eval.json"), "w") as f:
                    json.dump(out, f, indent=2)
            except OSError as e:
                raise HL.write_error(d, e, "write eval.json") from None
        if plot:
            plot(group_dir, cfgs, dirs, host, res)
    return states, group_dir, summaries


def resume_config(group_dir: str, overrides: dict) -> tuple:
    """(config, seeds) of a group to resume, with the schedule-only `overrides` applied."""
    g = read_group(group_dir)
    cfg = Config.from_dict(g["config"])
    allowed = {"total_env_steps", "total_episodes", "eval_every", "eval_episodes",
               "checkpoint_every", "keep_checkpoints"}
    bad = sorted(set(overrides) - allowed)
    if bad:
        raise ValueError(f"--resume cannot change {bad}: they change the state's shapes or the "
                         f"algorithm; allowed on resume: {sorted(allowed)}")
    return cfg.override(**overrides), tuple(g["seeds"])


def update_configs(group_dir: str, cfg: Config, seeds) -> None:
    """After a resume with a changed schedule: record it in group.json and each config.json."""
    g = read_group(group_dir)
    g["config"] = cfg.to_dict()
    try:
        atomic_write(os.path.join(group_dir, GROUP_FILE), json.dumps(g, indent=2, sort_keys=True))
    except OSError as e:
        raise HL.write_error(group_dir, e, f"update {GROUP_FILE}") from None
    for s in seeds:
        d = seed_dir(group_dir, s)
        payload = read_config(d)
        try:
            write_config(d, cfg.override(seed=s).to_dict(),
                         {k: v for k, v in payload.items() if k not in ("config", "versions")})
        except OSError as e:
            raise HL.write_error(d, e, "update config.json") from None

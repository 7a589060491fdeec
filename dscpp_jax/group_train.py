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
import math
import os
import signal
import sys
import time
from typing import Dict, Optional, Sequence

import numpy as np

from dscpp_jax.config import Config
from dscpp_jax.host_loop import Budget, TrainingDiverged, nonfinite_parts, on_main_thread
from dscpp_jax.run_dir import check_fresh, lock_run_dir
from dscpp_jax.run_logging import RunDirError

GROUP_FILE = "group.json"


def seed_dir(group_dir: str, seed: int) -> str:
    return os.path.join(group_dir, f"s{seed}")


def is_group_dir(path: str) -> bool:
    return os.path.isfile(os.path.join(path, GROUP_FILE))


def read_group(group_dir: str) -> dict:
    with open(os.path.join(group_dir, GROUP_FILE)) as f:
        return json.load(f)


def seed_dirs(group_dir: str) -> list[str]:
    """The seed directories of a group, in its seed order (from its group.json)."""
    return [seed_dir(group_dir, s) for s in read_group(group_dir)["seeds"]]


def group_of(run_dir: str) -> Optional[tuple]:
    """(group_dir, index in the group) when `run_dir` is a seed directory of a group, else None."""
    cfg_path = os.path.join(run_dir, "config.json")
    parent = os.path.dirname(os.path.abspath(os.path.normpath(run_dir)))
    if not (os.path.isfile(cfg_path) and is_group_dir(parent)):
        return None
    with open(cfg_path) as f:
        payload = json.load(f)
    if "group_index" not in payload:
        return None
    return parent, int(payload["group_index"])


def default_group_dir(cfg: Config, seeds: Sequence[int], root: str = "runs",
                      stamp: Optional[str] = None) -> str:
    from dscpp_jax.seed_group import format_seeds
    stamp = stamp or time.strftime("%Y%m%d-%H%M%S")
    return os.path.join(root, f"{cfg.env}-{cfg.algo}-g{format_seeds(seeds)}-{stamp}")


def _shared_stamp() -> str:
    """The same time stamp in every process (process 0's)."""
    import jax
    t = int(time.time())
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils
        t = int(multihost_utils.broadcast_one_to_all(np.int64(t)))
    return time.strftime("%Y%m%d-%H%M%S", time.localtime(t))


def _agree(flags: np.ndarray) -> np.ndarray:
    """Process 0's host decisions (stop, budget) in every process, so all stop together."""
    import jax
    if jax.process_count() == 1:
        return flags
    from jax.experimental import multihost_utils
    return np.asarray(multihost_utils.broadcast_one_to_all(flags))


def load_group(group_dir: str, step: Optional[int] = None):
    """(config of its first seed, group states) of a seed group's latest (or given) checkpoint,
    restored on this process's first device (as `dscpp_jax.seed_group.evaluate_group` takes)."""
    import jax

    from dscpp_jax import seed_group as SG
    from dscpp_jax.run_logging import read_config
    seeds = read_group(group_dir)["seeds"]
    cfg = Config.from_dict(read_config(seed_dir(group_dir, seeds[0]))["config"])
    like = SG.group_shapes(cfg, len(seeds))[2]   # as the group was trained (Warp's shared buffers too)
    ck = SG.GroupCheckpointer(group_dir)
    try:
        return cfg, ck.restore(like, SG.seed_mesh(jax.local_devices()[:1]), step)
    finally:
        ck.close()


def load_seed(run_dir: str, step: Optional[int] = None):
    """(config, state) of a seed directory of a group: the group checkpoint restored on this
    process's default device, seed taken out (an ordinary single-seed TrainState)."""
    import jax
    import jax.numpy as jnp

    from dscpp_jax import seed_group as SG
    from dscpp_jax.run_logging import read_config
    found = group_of(run_dir)
    if found is None:
        raise ValueError(f"{run_dir} is not a seed directory of a group")
    group_dir, index = found
    cfg = Config.from_dict(read_config(run_dir)["config"])
    _, states = load_group(group_dir, step)
    host = SG.index_tree(jax.device_get(states), index, SG.group_size(states))
    return cfg, jax.tree_util.tree_map(jnp.asarray, host)


def _write_group_json(group_dir: str, cfg: Config, seeds, mesh, extra=None) -> None:
    import jax

    from dscpp_jax.run_logging import library_versions
    payload = {"seeds": list(seeds), "config": cfg.override(seed=seeds[0]).to_dict(), "command": " ".join(sys.argv),
               "devices": [str(d) for d in jax.devices()], "mesh": {"seeds": int(mesh.size)},
               "process_count": jax.process_count(), "versions": library_versions()}
    payload.update(extra or {})
    with open(os.path.join(group_dir, GROUP_FILE), "w") as f:
        json.dump(payload, f, indent=2, sort_keys=True)


def _done(cfg: Config, env_steps: float, episodes: float) -> bool:
    """As cli._schedule_done, for one seed's host counters."""
    if env_steps >= cfg.total_env_steps:
        return True
    return cfg.total_episodes > 0 and episodes >= cfg.total_episodes


class GroupTooLarge(ValueError):
    """A seed group whose state would not fit in the memory of its devices or host."""


STATE_COPIES = 2
"""Group states a device holds at once while training: the state and the next one (the loop
keeps the previous state until the step's metrics are checked, to save it if they are not
finite)."""


def state_bytes(tree) -> int:
    """Bytes of the arrays of a (possibly abstract) pytree."""
    import jax
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
    import jax

    from dscpp_jax import seed_group as SG
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
            f"(replay_capacity={cfg.replay_capacity}, model_capacity={cfg.model_capacity}, "
            f"num_envs={cfg.num_envs}), so the group needs about {where}. Train at most {fit} "
            f"seeds at once, or lower replay_capacity / model_capacity. Nothing was written")
    return numbers


def train_group(cfg: Config, seeds: Sequence[int], group_dir: Optional[str] = None,
                resume: bool = False, time_budget: Optional[float] = None, progress: bool = True,
                max_iterations: Optional[int] = None, mesh=None, plot: bool = False,
                overwrite: bool = False):
    """Train (or resume) a seed group; returns (group state, group_dir, per-seed eval summaries).

    `cfg.seed` is ignored: seed i of the group uses seeds[i]. Stops when every seed's schedule is
    over (a seed that is done earlier is frozen where its separate run would have stopped), on
    Ctrl-C, at the time budget or at `max_iterations` group iterations. The final evaluation
    (eval.json of each seed; the summaries) belongs to the end of the schedule: a group that stops
    before every seed is done returns None for the summaries. The group directory is locked
    for this process; a fresh group refuses a directory that holds an earlier run unless
    `overwrite`, and one too large for the devices' memory is refused before anything is
    allocated (`check_group_memory`)."""
    import jax

    from dscpp_jax import seed_group as SG
    from dscpp_jax import trainer as T
    from dscpp_jax.cli import INBAND_LINE_EVERY, _is_ant, _previous_wall, chain_warnings
    from dscpp_jax import cli
    from dscpp_jax.run_logging import RunLogger, StartupClock, read_config, write_config

    clock = StartupClock(count_process=cli._FROM_COMMAND_LINE)
    budget = Budget(time_budget, count_process=cli._FROM_COMMAND_LINE)
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
    if _is_ant(cfg) and jax.default_backend() == "cpu":
        print(f"WARNING: {cfg.env} is an MJX ant environment meant for a GPU; on a CPU it is very "
              f"slow. Use a point-mass twin (e.g. point_{cfg.env}) for CPU runs.", file=sys.stderr)

    clock.mark("set-up")
    states = SG.init_group(seeds, cfg, mesh)
    jax.block_until_ready(states)
    clock.mark("env build and init")
    ckpt = SG.GroupCheckpointer(group_dir, keep=cfg.keep_checkpoints)
    restored = resume and ckpt.latest_step() is not None
    if restored:
        states = ckpt.restore(states, mesh)
        clock.mark("restore")
    c = SG.to_host(states.counters)
    env_steps = np.asarray(c.env_steps, float)
    episodes = np.asarray(c.episodes, float)
    iters = np.asarray(c.iteration, int)
    start_iter = int(iters.max())
    if restored:
        print(f"resumed group {group_dir} at iteration {start_iter} (seeds {list(seeds)})",
              file=sys.stderr)
    elif lead:
        env_cfg = dataclasses.asdict(T.make_env(cfg).config)
        _write_group_json(group_dir, cfg, seeds, mesh, {"env": env_cfg})
        for i, (d, c_) in enumerate(zip(dirs, cfgs)):
            write_config(d, c_.to_dict(), {"command": " ".join(sys.argv), "env": env_cfg,
                                           "group": os.path.abspath(group_dir),
                                           "group_index": i})
    loggers = [RunLogger(d, resume_iteration=int(it)) for d, it in zip(dirs, iters)] if lead else []
    walls = [_previous_wall(d) for d in dirs] if lead else [0.0] * n

    stop = {"flag": False}

    def on_sigint(signum, frame):
        if stop["flag"]:
            raise KeyboardInterrupt
        stop["flag"] = True
        print("\ninterrupt: finishing this iteration, saving a checkpoint of the group, then "
              "exiting (Ctrl-C again to abort without saving)", file=sys.stderr)

    old_handler = signal.signal(signal.SIGINT, on_sigint) if on_main_thread() else None
    pbar = None
    if progress and lead:
        try:
            from tqdm import tqdm
            pbar = tqdm(total=cfg.total_env_steps * n, initial=int(env_steps.sum()), unit="step",
                        dynamic_ncols=True, desc=f"{cfg.env}/{cfg.algo} x{n} seeds")
        except Exception:  # noqa: BLE001
            pbar = None
    t_start = time.time()
    # Warp's kernels build in a thread while XLA compiles the group step ahead of time (after
    # `init_group`; see `trainer.prewarm_physics`)
    clock.mark("set-up")
    prewarm = T.prewarm_physics(cfg.override(group_size=n))
    if prewarm is not None:
        fn, placed, all_active = SG.group_step_program(states, mesh)
        fn.lower(placed, all_active).compile()
        clock.mark("XLA compile ahead (group step)")
        prewarm.join()
        clock.mark("MuJoCo Warp kernels left")
    first = True
    last_eval = np.full((n,), np.nan)
    warned = [set() for _ in range(n)]   # chain warnings printed, per seed (each kind once)
    inband = np.full((n,), np.nan)     # in-band success per seed (NaN: none finished yet)
    options = np.full((n,), np.nan)
    saved_iter = start_iter
    group_it = start_iter
    pending: Dict[int, dict] = {}   # seed index -> its last row, waiting for an evaluation
    try:
        while True:
            active = np.array([not _done(c_, e, p) for c_, e, p in zip(cfgs, env_steps, episodes)])
            if not active.any():
                break
            if max_iterations is not None and group_it - start_iter >= max_iterations:
                break
            if _agree(np.array([budget.no_room()]))[0]:
                print(budget.reached_text(), file=sys.stderr)
                break
            prev = states
            t0 = time.time()
            states, m = SG.train_step_group(states, active, mesh)
            m = {k: np.asarray(v, float) for k, v in SG.to_host(m).items()}
            dt = time.time() - t0
            if first:
                first = False
                clock.mark("first iteration")
                if lead:
                    cli._write_startup(clock, group_dir, pbar, group_iteration=group_it + 1,
                                   resumed_at_iteration=start_iter, seeds=list(seeds),
                                   physics=T.resolve_physics(cfg).physics,
                                   device=str(jax.devices()[0].device_kind))
            bad = {seeds[i]: b for i in range(n) if active[i]
                   for b in [nonfinite_parts({k: v[i] for k, v in m.items()})] if b}
            if bad:
                if saved_iter != group_it or ckpt.latest_step() is None:
                    ckpt.save(group_it, prev)
                which = "; ".join(f"seed {s}: {b}" for s, b in bad.items())
                raise TrainingDiverged(
                    f"learning diverged at iteration {group_it + 1} ({which}); the whole group "
                    f"stopped. The last finite group state was saved (iteration {group_it}) under "
                    f"{group_dir}/checkpoints. Lower the learning rates (td3_lr, dyn_lr) or the "
                    f"updates per step, or start a group without seed(s) {sorted(bad)}.")
            group_it += 1
            env_steps = np.where(active, m["counters/env_steps"], env_steps)
            episodes = np.where(active, m["counters/episodes"], episodes)
            finished = active & np.array([_done(c_, e, p) for c_, e, p in
                                          zip(cfgs, env_steps, episodes)])
            its = np.where(active, m["counters/iteration"], iters).astype(int)
            iters = its
            periodic = active & ((its % cfg.eval_every == 0) if cfg.eval_every
                                 else np.zeros((n,), bool))
            due = periodic | (finished & bool(cfg.eval_every))
            # A seed that just finished is frozen, so its evaluation gives the same numbers at any
            # later point (the key comes from its iteration): evaluate now only when a periodic
            # evaluation is due anyway, else leave its last row pending until the next evaluation
            # of the group or the final one, instead of one evaluation per finishing seed.
            ev = None
            if periodic.any():
                ev, _ = SG.evaluate_group(states, mesh=mesh)
                _flush_pending(pending, ev, loggers, last_eval)
            if "options/num_options" in m:
                options = np.where(active, m["options/num_options"], options)
            per_seed_rate = cfg.steps_per_iteration_total / max(dt, 1e-9)
            for i in range(n):
                if not active[i]:
                    continue
                row = {"iteration": int(its[i]), "env_steps": env_steps[i], "episodes": episodes[i],
                       "wall_clock": walls[i] + time.time() - t_start, "time/iteration_s": dt,
                       "time/env_steps_per_s": per_seed_rate,
                       "time/group_env_steps_per_s": per_seed_rate * int(active.sum())}
                row.update({k: float(v[i]) for k, v in m.items()
                            if not k.startswith("counters/")})
                if due[i] and ev is None:
                    pending[i] = row
                    continue
                if due[i]:
                    row.update(ev[i])
                    last_eval[i] = ev[i]["eval/success_rate"]
                if lead:
                    loggers[i].log(row)
                    for kind, msg in chain_warnings(
                            row, cfgs[i], f"seed {seeds[i]}, iteration {int(its[i])}: "):
                        if kind not in warned[i]:
                            warned[i].add(kind)
                            (pbar.write if pbar is not None else print)(msg, file=sys.stderr)
            if "inband/success_rate" in m:
                seen = active & (m["inband/window"] > 0)
                inband = np.where(seen, m["inband/success_rate"], np.where(active, np.nan, inband))
            rate = per_seed_rate * int(active.sum())
            ib = {} if not np.isfinite(inband).any() else {
                "inband_mean": f"{np.nanmean(inband):.2f}"}
            if lead and pbar is not None:
                pbar.update(int(env_steps.sum()) - pbar.n)
                pbar.set_postfix(eval_mean=f"{np.nanmean(last_eval):.2f}" if np.isfinite(
                    last_eval).any() else "nan",
                    eval_min=f"{np.nanmin(last_eval):.2f}" if np.isfinite(last_eval).any() else "nan",
                    **ib, options=_range(options), steps_per_s=f"{rate:.0f}", refresh=False)
            elif lead and (ev is not None or (ib and group_it % INBAND_LINE_EVERY == 0)):
                ib_text = f" inband_success mean {ib['inband_mean']}" if ib else ""
                ev_text = (f"eval_success mean {np.nanmean(last_eval):.2f} min "
                           f"{np.nanmin(last_eval):.2f}" if np.isfinite(last_eval).any()
                           else "eval_success -")
                print(f"[{time.time() - t_start:7.0f}s] it {group_it} env_steps/seed "
                      f"{int(env_steps.max())} episodes/seed {_range(episodes)} {ev_text}{ib_text} "
                      f"options {_range(options)} steps/s (all seeds) {rate:.0f}", flush=True)
            if cfg.checkpoint_every and group_it % cfg.checkpoint_every == 0:
                ckpt.save(group_it, states, wait=False)   # written while the next iterations run
                saved_iter = group_it
            budget.iteration_took(time.time() - t0)
            if _agree(np.array([stop["flag"]]))[0]:
                break
        if group_it != saved_iter or ckpt.latest_step() is None:
            t0 = time.time()
            ckpt.save(group_it, states)
            budget.save_took(time.time() - t0)
        if stop["flag"]:
            print(f"saved a checkpoint of the group at iteration {group_it}; continue with "
                  f"--resume {group_dir}", file=sys.stderr)
        summaries = res = None
        if all(_done(c_, e, p) for c_, e, p in zip(cfgs, env_steps, episodes)):
            summaries, res = SG.evaluate_group(states, num_episodes=cfg.eval_episodes, mesh=mesh)
            _flush_pending(pending, summaries, loggers, last_eval)
    finally:
        _flush_pending(pending, None, loggers, last_eval)   # on an error: the rows, no evaluation
        if pbar is not None:
            pbar.close()
        for lg in loggers:
            lg.close()
        ckpt.close()
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)

    c = SG.to_host(states.counters)               # collectives: every process takes part
    if summaries is None:
        return states, group_dir, None
    host = SG.to_host(states) if plot else None
    if lead:
        for i, d in enumerate(dirs):
            out = dict(summaries[i], iteration=int(c.iteration[i]), env_steps=int(c.env_steps[i]),
                       episodes_trained=int(c.episodes[i]), seed=seeds[i])
            with open(os.path.join(d, "eval.json"), "w") as f:
                json.dump(out, f, indent=2)
        if plot:
            _plot_group(group_dir, cfgs, dirs, host, res)
    return states, group_dir, summaries


def _flush_pending(pending: Dict[int, dict], ev, loggers, last_eval) -> None:
    """Log the rows left waiting for an evaluation, with seed i's numbers from `ev[i]`."""
    for i, row in sorted(pending.items()):
        if ev is not None:
            row.update(ev[i])
            last_eval[i] = ev[i]["eval/success_rate"]
        if loggers:
            loggers[i].log(row)
    pending.clear()


def _range(x) -> str:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not x.size:
        return "-"
    lo, hi = int(x.min()), int(x.max())
    return str(lo) if lo == hi else f"{lo}-{hi}"


def _plot_group(group_dir, cfgs, dirs, host, res) -> None:
    """Plots of a group from its host copy `host` (process 0 only)."""
    from dscpp_jax import plots
    from dscpp_jax import seed_group as SG
    c = host.counters
    n = len(dirs)
    plots.plot_curves(dirs, os.path.join(group_dir, "plots", "curves.png"))
    for i, (cfg, d) in enumerate(zip(cfgs, dirs)):
        out = os.path.join(d, "plots")
        plots.plot_curves([d], os.path.join(out, "curves.png"))
        plots.plot_trajectory(cfg, SG.index_tree(res, i), os.path.join(out, "trajectory.png"),
                              title=f"{cfg.env} {cfg.algo} seed {cfg.seed}, iteration "
                                    f"{int(c.iteration[i])}, {int(c.env_steps[i])} env steps")
        plots.plot_classifiers(cfg, SG.index_tree(host, i, n), os.path.join(out, "classifiers.png"))


def resume_config(group_dir: str, overrides: dict) -> tuple:
    """(config, seeds) of a group to resume, with the schedule-only `overrides` applied."""
    g = read_group(group_dir)
    cfg = Config.from_dict(g["config"])
    allowed = {"total_env_steps", "total_episodes", "eval_every", "eval_episodes",
               "checkpoint_every", "keep_checkpoints", "log_every"}
    bad = sorted(set(overrides) - allowed)
    if bad:
        raise ValueError(f"--resume cannot change {bad}: they change the state's shapes or the "
                         f"algorithm; allowed on resume: {sorted(allowed)}")
    return cfg.override(**overrides), tuple(g["seeds"])


def update_configs(group_dir: str, cfg: Config, seeds) -> None:
    """After a resume with a changed schedule: record it in group.json and each config.json."""
    from dscpp_jax.run_logging import read_config, write_config
    g = read_group(group_dir)
    g["config"] = cfg.to_dict()
    with open(os.path.join(group_dir, GROUP_FILE), "w") as f:
        json.dump(g, f, indent=2, sort_keys=True)
    for s in seeds:
        d = seed_dir(group_dir, s)
        payload = read_config(d)
        write_config(d, cfg.override(seed=s).to_dict(),
                     {k: v for k, v in payload.items() if k not in ("config", "versions")})

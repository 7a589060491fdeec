"""The run directory as a unit that one process owns, and the reading of what a run left there.

Owning (`train`):

    lock_run_dir(path)      the lock file RUN_DIR/.lock, held (flock) until the process exits;
                            a second process on the same directory gets a RunDirLocked naming
                            the holder's PID
    existing_run(path)      what of an earlier run the directory holds (config.json, ...)
    check_fresh(path, ...)  refuse an existing run unless asked to overwrite it, then clear it

Reading (`eval`, `plot`, `video`, `diagnose`, `compare` and the API):

    load_run(path, step)    (config, state) of a run's checkpoint; a seed directory of a group
                            restores the group checkpoint and takes its seed out
    saved_config(path)      the config a run or group saved, read without touching JAX
    is_group_dir, read_group, seed_dir, seed_dirs, group_of, load_group, load_seed
                            a seed group's directory: group.json and one run directory per seed
"""
from __future__ import annotations

import fcntl
import json
import os
import shutil
import time
from typing import Dict, List, Optional

import jax
import jax.numpy as jnp

from dscpp_jax import checkpoint as ck
from dscpp_jax import seed_group as SG
from dscpp_jax import trainer as T
from dscpp_jax.config import Config, flat_config
from dscpp_jax.run_logging import RunDirError, load_config, read_config, read_metrics

LOCK_FILE = ".lock"

RUN_FILES = ("config.json", "metrics.csv", "group.json", "checkpoints")
"""Any of these in a directory means a run was started there."""

CLEARED = ("config.json", "metrics.csv", "group.json", "checkpoints", "checkpoints_unrestorable",
           "startup.jsonl", "tb", "plots", "videos", "wandb_run.json", "wandb")
"""What `clear_run` removes (with every eval*.json and eval*.png, and a group's seed
directories): the files `train`, `eval`, `plot` and `video` write."""

_HELD: Dict[str, int] = {}   # absolute lock path -> the open descriptor that holds the lock


class RunDirLocked(RunDirError):
    """Another process is training in this run directory."""


def lock_run_dir(path: str) -> str:
    """Take the exclusive lock of run (or seed-group) directory `path` (created if missing) for
    the rest of this process; a second call from this process on the same directory is a no-op.
    Raises RunDirLocked, naming the other process's PID, when another process holds it. Returns
    the lock file's path."""
    os.makedirs(path, exist_ok=True)
    lock = os.path.abspath(os.path.join(path, LOCK_FILE))
    if lock in _HELD:
        return lock
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        try:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
        finally:
            os.close(fd)
        raise RunDirLocked(f"{path} is in use by another process (PID {holder}) that trains in "
                           f"it; wait for it to end or stop it, or pick another --run-dir"
                           ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _HELD[lock] = fd
    return lock


def unlock_run_dir(path: str) -> None:
    """Give up this process's lock of `path` (if it holds it)."""
    lock = os.path.abspath(os.path.join(path, LOCK_FILE))
    fd = _HELD.pop(lock, None)
    if fd is not None:
        os.close(fd)   # closing the descriptor releases the flock


def existing_run(path: str) -> List[str]:
    """The names in `path` that show an earlier run was started there (config.json, metrics.csv,
    group.json, checkpoints/); [] for a missing or empty directory."""
    return [n for n in RUN_FILES if os.path.exists(os.path.join(path, n))]


def _group_seed_dirs(path: str) -> List[str]:
    """The seed directories (sN/ holding a config.json) of a group directory."""
    out = []
    try:
        names = os.listdir(path)
    except OSError:
        return out
    for n in names:
        d = os.path.join(path, n)
        if n.startswith("s") and n[1:].isdigit() and os.path.isfile(os.path.join(d, "config.json")):
            out.append(d)
    return out


def clear_run(path: str) -> None:
    """Remove an earlier run's files from `path` (see `CLEARED`), so that nothing of it is left
    for a new run to mix with; other files, and the lock, stay."""
    seed_dirs = _group_seed_dirs(path)
    for d in seed_dirs:
        shutil.rmtree(d)
    for n in os.listdir(path):
        p = os.path.join(path, n)
        if n in CLEARED or (n.startswith("eval") and n.endswith((".json", ".png"))):
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p)
            else:
                os.unlink(p)


def check_fresh(path: str, overwrite: bool = False) -> None:
    """Before a fresh run writes into `path`: refuse (RunDirError) when it holds an earlier run,
    unless `overwrite`, which clears that run first (`clear_run`)."""
    found = existing_run(path)
    if not found:
        return
    if not overwrite:
        raise RunDirError(f"{path} already holds a run ({', '.join(found)}): continue it with "
                          f"`train --resume {path}`, start it over with --overwrite (deletes its "
                          f"checkpoints and logs), or pick another --run-dir")
    clear_run(path)


# ------------------------------------------------------------------------------------------------
# Reading a run directory
# ------------------------------------------------------------------------------------------------
GROUP_FILE = "group.json"


def seed_dir(group_dir: str, seed: int) -> str:
    """The run directory of seed `seed` inside a seed group's directory."""
    return os.path.join(group_dir, f"s{seed}")


def is_group_dir(path: str) -> bool:
    """Whether `path` is a seed group's directory (it holds group.json)."""
    return os.path.isfile(os.path.join(path, GROUP_FILE))


def read_group(group_dir: str) -> dict:
    """A seed group's group.json (seeds, config, command, devices, ...)."""
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


def default_run_dir(cfg: Config, root: str = "runs") -> str:
    """runs/<env>-<algo>-s<seed>-<time>: where a fresh run goes without --run-dir."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return os.path.join(root, f"{cfg.env}-{cfg.algo}-s{cfg.run.seed}-{stamp}")


def saved_config(run_dir: str) -> Optional[dict]:
    """The config saved in a run's config.json or a group's group.json as {flat name: value}
    (`config.flat_config`), read without touching JAX; None when there is none to read."""
    for name in ("config.json", GROUP_FILE):
        try:
            with open(os.path.join(run_dir, name)) as f:
                return flat_config(dict(json.load(f)["config"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return None


def previous_wall(run_dir: str) -> float:
    """The last wall-clock second that the run's metrics.csv recorded (0 for a fresh run): a
    resumed run's clock continues from it."""
    try:
        w = [x for x in read_metrics(run_dir).get("wall_clock", []) if x == x]
        return float(w[-1]) if w else 0.0
    except FileNotFoundError:
        return 0.0


def load_group(group_dir: str, step: Optional[int] = None):
    """(config of its first seed, group states) of a seed group's latest (or given) checkpoint,
    restored on this process's first device (as `dscpp_jax.seed_group.evaluate_group` takes)."""
    seeds = read_group(group_dir)["seeds"]
    cfg = Config.from_dict(read_config(seed_dir(group_dir, seeds[0]))["config"])
    like = SG.group_shapes(cfg, len(seeds))[2]   # as the group was trained (Warp's shared buffers too)
    checkpointer = SG.GroupCheckpointer(group_dir)
    try:
        return cfg, checkpointer.restore(like, SG.seed_mesh(jax.local_devices()[:1]), step)
    finally:
        checkpointer.close()


def load_seed(run_dir: str, step: Optional[int] = None):
    """(config, state) of a seed directory of a group: the group checkpoint restored on this
    process's default device, seed taken out (an ordinary single-seed TrainState)."""
    found = group_of(run_dir)
    if found is None:
        raise ValueError(f"{run_dir} is not a seed directory of a group")
    group_dir, index = found
    cfg = Config.from_dict(read_config(run_dir)["config"])
    _, states = load_group(group_dir, step)
    host = SG.index_tree(jax.device_get(states), index, SG.group_size(states))
    return cfg, jax.tree_util.tree_map(jnp.asarray, host)


def load_run(run_dir: str, step: Optional[int] = None):
    """(config, state) of a run directory's latest (or given) checkpoint; a seed directory of a
    group gives its seed of the group checkpoint (`load_seed`)."""
    if group_of(run_dir) is not None:   # a seed directory inside a seed group
        return load_seed(run_dir, step)
    if is_group_dir(run_dir):
        raise ValueError(f"{run_dir} is a seed group; name one of its seeds, e.g. "
                         f"{os.path.join(run_dir, 's%d' % read_group(run_dir)['seeds'][0])}")
    cfg = load_config(run_dir)
    try:
        state = ck.restore_state(run_dir, T.init(jax.random.PRNGKey(cfg.run.seed), cfg), step)
    except ck.NoCheckpointError as e:
        raise ck.NoCheckpointError(f"run {run_dir} has no checkpoint to load ({e})") from None
    return cfg, state

"""The run directory as a unit that one process owns: an exclusive lock, the check that a fresh
run never writes over an existing one, and the clearing that `--overwrite` asks for.

    lock_run_dir(path)      the lock file RUN_DIR/.lock, held (flock) until the process exits;
                            a second process on the same directory gets a RunDirLocked naming
                            the holder's PID
    existing_run(path)      what of an earlier run the directory holds (config.json, ...)
    check_fresh(path, ...)  refuse an existing run unless asked to overwrite it, then clear it
"""
from __future__ import annotations

import fcntl
import os
import shutil
from typing import Dict, List

from dscpp_jax.run_logging import RunDirError

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

"""Whole-state checkpoints with orbax: every array of the TrainState (params, optimizer and target
states, normalisers, replay buffers, option table and classifiers, counters, PRNG key).

Typed PRNG keys are stored as their raw key data (`jax.random.key_data`) and re-wrapped on restore,
so a checkpoint written on one JAX version restores on another.

Safety: a new checkpoint is read back before any older one is deleted (orbax itself would delete
the oldest as soon as the new one is written), so a save that fails, or writes damaged files,
never leaves a run with only a broken checkpoint. Restoring the latest checkpoint falls back to
the newest one that restores, with a warning on stderr naming both steps.

Training saves in the background (`save(..., wait=False)`): the call returns once the state is
copied to host memory (numpy); orbax's save, the write, the read-back and the pruning run on a
worker thread that touches no device, while the next iterations run. Its outcome is collected by
the next `save`, `wait` or `close`, which raise its CheckpointError, if any; until then the older
checkpoints stay, as with a save that fails.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import sys
import threading
import time
import traceback
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from dscpp_jax.run_logging import os_error_fix

CKPT_DIR = "checkpoints"


class _NoFalseWaitWarning(logging.Filter):
    """Drops orbax's "Waiting for previous save to complete took N seconds" warning. Every save
    here waits for its own write to finish (`wait_until_finished`), and orbax counts that wait
    against the next save, so the warning fires at every checkpoint of a large state without
    anything having waited for a previous save."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Waiting for previous save to complete")


class _NoOrbaxTracebacks(logging.Filter):
    """Drops the errors (with their tracebacks) that orbax logs from its save and finalize
    threads, and asyncio's reports of the same failures: every one of them also reaches the
    `Checkpointer` call that waits for the save, which raises a one-line CheckpointError naming
    the cause and the fix. Without this a full disk prints hundreds of lines of tracebacks around
    that line."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.ERROR:
            return True
        return not ("orbax" in (record.pathname or "") or record.name == "asyncio")


def closed_loop_report(unraisable) -> bool:
    """Whether an exception handed to `sys.unraisablehook` is asyncio's "Event loop is closed"
    from `call_soon_threadsafe`: tensorstore finishing a write of a save that failed, after orbax
    closed the event loop that waited for it. A failed save leaves one such report per array
    still being written (hundreds of tracebacks on a full disk), each printed by the default
    hook; the failure itself reaches the `Checkpointer` call that waits for the save."""
    if unraisable.exc_type is not RuntimeError or "Event loop is closed" not in str(
            unraisable.exc_value):
        return False
    frames = traceback.extract_tb(unraisable.exc_traceback)
    return bool(frames) and all(os.path.basename(f.filename) == "base_events.py" and
                                os.path.basename(os.path.dirname(f.filename)) == "asyncio"
                                for f in frames)


class _NoClosedLoopReports:
    """`sys.unraisablehook` that drops `closed_loop_report`s and hands the rest to the hook it
    replaced."""

    def __init__(self, previous):
        self.previous = previous

    def __call__(self, unraisable) -> None:
        if not closed_loop_report(unraisable):
            self.previous(unraisable)


def quiet_orbax() -> None:
    """Install the filters on absl's logger (orbax logs through absl) and asyncio's, and the
    `sys.unraisablehook` that drops a failed save's closed-loop reports, once per process (the
    hook again where something replaced it since)."""
    logger = logging.getLogger("absl")
    if not any(isinstance(f, _NoFalseWaitWarning) for f in logger.filters):
        logger.addFilter(_NoFalseWaitWarning())
    for name in ("absl", "asyncio"):
        lg = logging.getLogger(name)
        if not any(isinstance(f, _NoOrbaxTracebacks) for f in lg.filters):
            lg.addFilter(_NoOrbaxTracebacks())
    if not isinstance(sys.unraisablehook, _NoClosedLoopReports):
        sys.unraisablehook = _NoClosedLoopReports(sys.unraisablehook)


def _is_typed_key(x: Any) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _empty(x: Any) -> bool:
    return hasattr(x, "shape") and int(np.prod(np.shape(x))) == 0


def to_storable(tree: Any) -> Any:
    """Replace typed PRNG keys by their uint32 key data, and zero-size arrays (which orbax refuses,
    e.g. an empty MJX actuator-activation vector) by a one-element placeholder."""
    def conv(x):
        if _is_typed_key(x):
            return jax.random.key_data(x)
        if _empty(x):
            return jnp.zeros((1,), x.dtype)
        return x
    return jax.tree_util.tree_map(conv, tree)


def from_storable(stored: Any, like: Any) -> Any:
    """Inverse of `to_storable`, using `like` (same structure) to know where keys were."""
    def back(s, l):
        if _empty(l):
            return jnp.zeros(np.shape(l), l.dtype)
        if _is_typed_key(l):
            try:
                impl = jax.random.key_impl(l)
            except Exception:  # noqa: BLE001 - abstract `like`: default implementation
                impl = None
            return jax.random.wrap_key_data(jnp.asarray(s), impl=impl)
        return s
    return jax.tree_util.tree_map(back, stored, like)


OPTIONAL_FIELDS = ("inband",)
"""TrainState fields that are None unless a feature is on (in-band evaluation)."""


def as_stored(tree: Any) -> Any:
    """The tree orbax writes: a TrainState as a dict of its array fields, an optional field left
    out where it is None, so that a state without the feature has the layout of checkpoints
    written before the field existed (and restores them). Any other tree as it is."""
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type) and hasattr(tree, "counters"):
        return {f.name: getattr(tree, f.name) for f in dataclasses.fields(tree)
                if f.metadata.get("pytree_node", True)
                and not (f.name in OPTIONAL_FIELDS and getattr(tree, f.name) is None)}
    return tree


def from_stored(stored: Any, like: Any) -> Any:
    """Inverse of `as_stored`: `like` with the restored fields."""
    if isinstance(stored, dict) and not isinstance(like, dict):
        return like.replace(**stored)
    return stored


def _abstract(tree: Any) -> Any:
    return jax.eval_shape(lambda t: as_stored(to_storable(t)), tree)


class CheckpointError(ValueError):
    """A checkpoint cannot be written or restored; the message says what to do."""


NONE_SAVED = ("the run saved none yet, or this is a copy without checkpoints (results "
              "directories keep metrics.csv, config.json and eval.json only); train (or resume) "
              "it first, or point at the run directory that training wrote")


class NoCheckpointError(CheckpointError, FileNotFoundError):
    """The run directory has no checkpoint (yet)."""


UNRESTORABLE_DIR = "checkpoints_unrestorable"


def _reason(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:300]}" + ("..." if len(text) > 300 else "")


def save_error(e: BaseException, directory: str, run_dir: str, step: int | None = None,
               kept: list[int] | None = None) -> CheckpointError:
    """The one-line CheckpointError for a save under `directory` (the checkpoints of run or
    group directory `run_dir`) that failed with `e` (any type: orbax and tensorstore wrap a full
    disk in several): the step, the cause, which checkpoints are left and the fix."""
    what = f"the checkpoint of iteration {step}" if step is not None else "a checkpoint"
    left = (f"the earlier checkpoints (iterations {kept}) were kept" if kept else
            "no earlier checkpoint exists" if kept is not None else "the earlier checkpoints "
            "were kept")
    return CheckpointError(f"could not save {what} under {directory} ({_reason(e)}); {left}. "
                           f"Fix: {os_error_fix(e, directory, run_dir)}")


class Checkpointer:
    """Periodic whole-state checkpoints under RUN_DIR/checkpoints/<step>/ (step = iteration).

    Keeps the newest `keep` checkpoints; older ones are deleted only after a new checkpoint has
    been written and read back (`verify`)."""

    def __init__(self, run_dir: str, keep: int = 2, verify: bool = True):
        self.run_dir = run_dir
        self.directory = os.path.abspath(os.path.join(run_dir, CKPT_DIR))
        self.keep = max(1, int(keep))
        self.verify = verify
        # max_to_keep=None: orbax deletes nothing; `_prune` does, once the new step reads back
        quiet_orbax()
        opts = ocp.CheckpointManagerOptions(max_to_keep=None, create=True)
        self.manager = ocp.CheckpointManager(self.directory, options=opts)
        self._worker: threading.Thread | None = None   # a save finishing in the background
        self._worker_error: BaseException | None = None

    def all_steps(self) -> list[int]:
        self._join()
        return self._steps()

    def _steps(self) -> list[int]:
        return sorted(int(s) for s in self.manager.all_steps())

    def save(self, step: int, state: Any, force: bool = True, wait: bool = True) -> None:
        """Write, read back, then prune. A failure raises a CheckpointError (older checkpoints
        stay as they were); a step that is already saved is left alone.

        `wait=False` returns once the state is in host memory and finishes on a worker thread;
        the next `save`, `wait` or `close` waits for it and raises its error."""
        self.wait()
        step = int(step)
        if step in self._steps():
            return
        stored = as_stored(to_storable(state))
        abstract = _abstract(state)
        if wait:
            self._write(step, stored, force)
            self._finish(step, abstract)
            return
        # The loop waits only for the copy to host memory. orbax's own part of a save (on an
        # H200 about 0.5 s for a U-maze run's 344 arrays) runs on the worker with the rest.
        host = jax.device_get(stored)

        def work():
            try:
                self._write(step, host, force)
                self._finish(step, abstract)
            except BaseException as e:  # noqa: BLE001 - handed to the thread that waits
                self._worker_error = e
        self._worker = threading.Thread(target=work, name=f"checkpoint-{step}", daemon=False)
        self._worker.start()

    def _write(self, step: int, stored: Any, force: bool) -> None:
        try:
            self.manager.save(step, args=ocp.args.StandardSave(stored), force=force)
        except Exception as e:  # noqa: BLE001 - orbax / tensorstore wrap OSErrors in many types
            raise self._save_error(step, e) from e

    def wait(self) -> None:
        """Wait for a save still finishing in the background; raise its CheckpointError."""
        self._join()
        err, self._worker_error = self._worker_error, None
        if err is not None:
            raise err

    def _join(self) -> None:
        if self._worker is not None:
            self._worker.join()
            self._worker = None

    def _save_error(self, step: int, e: BaseException) -> CheckpointError:
        return save_error(e, self.directory, self.run_dir, step, self._steps())

    def _finish(self, step: int, like: Any) -> None:
        """The part of a save after orbax's `save` call: the write's end, read-back, pruning.
        Touches no device (`like` is abstract; the read-back lands in numpy arrays)."""
        try:
            self.manager.wait_until_finished()
        except Exception as e:  # noqa: BLE001
            raise self._save_error(step, e) from e
        if self.verify:
            try:
                self._read_back(step, like)
            except Exception as e:  # noqa: BLE001
                moved = self._set_aside(step)
                raise CheckpointError(
                    f"the checkpoint of iteration {step} did not read back ({_reason(e)}); it was "
                    f"moved to {moved} and {self._kept()}. Check the disk under {self.directory} "
                    f"and continue with `train --resume {self.run_dir}`") from e
        self._prune(step)

    def _kept(self) -> str:
        steps = self._steps()
        return (f"the earlier checkpoints (iterations {steps}) were kept" if steps else
                "no earlier checkpoint exists")

    def _read_back(self, step: int, like: Any) -> None:
        """Restore `step` to host memory (numpy), which reads and decodes every stored array."""
        abstract = _abstract(like)
        target = jax.tree_util.tree_map(lambda a: np.empty(a.shape, a.dtype), abstract)
        self.manager.restore(step, args=ocp.args.StandardRestore(target))

    def _prune(self, newest: int) -> None:
        older = [s for s in self._steps() if s < newest]
        for s in older[:max(0, len(older) - (self.keep - 1))]:
            self.manager.delete(s)

    def _set_aside(self, step: int) -> str:
        """Move a damaged checkpoint out of the way (never delete it): RUN/checkpoints_unrestorable/."""
        src = os.path.join(self.directory, str(step))
        dst_dir = os.path.join(os.path.dirname(self.directory), UNRESTORABLE_DIR)
        dst = os.path.join(dst_dir, f"{step}-{time.strftime('%Y%m%d-%H%M%S')}")
        try:
            os.makedirs(dst_dir, exist_ok=True)
            shutil.move(src, dst)
            self.manager.reload()
        except OSError:
            return src + " (could not move it)"
        return dst

    def latest_step(self) -> int | None:
        self._join()
        return self.manager.latest_step()

    def restore(self, like: Any, step: int | None = None, set_aside_broken: bool = False) -> Any:
        """Restore into the structure of `like` (a concrete state or `jax.eval_shape` output).

        With `step=None`, the newest checkpoint that restores: a newer one that does not is
        reported on stderr (and with `set_aside_broken`, moved to RUN/checkpoints_unrestorable/,
        so that training can write that iteration again)."""
        steps = self.all_steps()
        if step is not None:
            if int(step) not in steps:
                raise NoCheckpointError(f"no checkpoint of iteration {step} under {self.directory}"
                                        f"; saved iterations: {steps}")
            return self._restore(like, int(step))
        if not steps:
            raise NoCheckpointError(f"no checkpoint found under {self.directory}: {NONE_SAVED}")
        failures = []
        for s in reversed(steps):
            try:
                out = self._restore(like, s)
            except Exception as e:  # noqa: BLE001 - damaged files surface as many error types
                failures.append((s, e))
                continue
            if failures:
                bad = ", ".join(f"{b} ({_reason(e)})" for b, e in failures)
                note = ""
                if set_aside_broken:
                    note = "; moved aside: " + ", ".join(self._set_aside(b) for b, _ in failures)
                print(f"WARNING: the newest checkpoint(s) under {self.directory} cannot be "
                      f"restored: iteration {bad}. Using iteration {s} instead{note}.",
                      file=sys.stderr, flush=True)
            return out
        bad = "; ".join(f"iteration {b}: {_reason(e)}" for b, e in failures)
        raise CheckpointError(
            f"no checkpoint under {self.directory} restores ({bad}). The files are damaged, or the "
            f"run was saved by a version whose state differs from this one's; start a new run")

    def _restore(self, like: Any, step: int) -> Any:
        stored = self.manager.restore(step, args=ocp.args.StandardRestore(_abstract(like)))
        # uncommitted default-device arrays, like the outputs of `init` and `train_step`, so the
        # next call of a jitted function hits its compilation cache
        stored = jax.tree_util.tree_map(lambda x: jnp.asarray(np.asarray(x)), stored)
        return from_stored(from_storable(stored, as_stored(like)), like)

    def close(self) -> None:
        """Wait for a save still finishing, then close the manager; raises the first error (a
        CheckpointError), and only that one: orbax raises a failed save's error again at each
        later wait."""
        err = None
        try:
            self.wait()
        except BaseException as e:  # noqa: BLE001 - raised below, after closing
            err = e
        for step in (self.manager.wait_until_finished, self.manager.close):
            try:
                step()
            except Exception as e:  # noqa: BLE001
                if err is None:
                    err = CheckpointError(
                        f"could not finish writing a checkpoint under {self.directory} "
                        f"({_reason(e)}); {self._kept()}. Fix: "
                        f"{os_error_fix(e, self.directory, self.run_dir)}")
        if err is not None:
            raise err


def save_state(run_dir: str, step: int, state: Any, keep: int = 2) -> None:
    ck = Checkpointer(run_dir, keep)
    try:
        ck.save(step, state)
    finally:
        ck.close()


def restore_state(run_dir: str, like: Any, step: int | None = None,
                  set_aside_broken: bool = False) -> Any:
    if not os.path.isdir(os.path.join(run_dir, CKPT_DIR)):
        raise NoCheckpointError(f"no checkpoint found under {os.path.join(run_dir, CKPT_DIR)}: "
                                f"{NONE_SAVED}")
    ck = Checkpointer(run_dir)
    try:
        return ck.restore(like, step, set_aside_broken=set_aside_broken)
    finally:
        ck.close()


def latest_step(run_dir: str) -> int | None:
    d = os.path.join(run_dir, CKPT_DIR)
    if not os.path.isdir(d):
        return None
    ck = Checkpointer(run_dir)
    try:
        return ck.latest_step()
    finally:
        ck.close()


def all_steps(run_dir: str) -> list[int]:
    """The iterations saved under RUN_DIR/checkpoints (oldest first)."""
    d = os.path.join(run_dir, CKPT_DIR)
    if not os.path.isdir(d):
        return []
    ck = Checkpointer(run_dir)
    try:
        return ck.all_steps()
    finally:
        ck.close()

"""Whole-state checkpoints with orbax: every array of the TrainState (params, optimizer and target
states, normalisers, replay buffers, option table and classifiers, counters, PRNG key).

Typed PRNG keys are stored as their raw key data (`jax.random.key_data`) and re-wrapped on restore,
so a checkpoint written on one JAX version restores on another.
"""
from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

CKPT_DIR = "checkpoints"


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


def _abstract(tree: Any) -> Any:
    return jax.eval_shape(to_storable, tree)


class Checkpointer:
    """Periodic whole-state checkpoints under RUN_DIR/checkpoints/<step>/ (step = iteration)."""

    def __init__(self, run_dir: str, keep: int = 2):
        self.directory = os.path.abspath(os.path.join(run_dir, CKPT_DIR))
        opts = ocp.CheckpointManagerOptions(max_to_keep=max(1, keep), create=True)
        self.manager = ocp.CheckpointManager(self.directory, options=opts)

    def save(self, step: int, state: Any, force: bool = True) -> None:
        self.manager.save(int(step), args=ocp.args.StandardSave(to_storable(state)), force=force)
        self.manager.wait_until_finished()

    def latest_step(self) -> int | None:
        return self.manager.latest_step()

    def restore(self, like: Any, step: int | None = None) -> Any:
        """Restore into the structure of `like` (a concrete state or `jax.eval_shape` output)."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint found under {self.directory}")
        stored = self.manager.restore(step, args=ocp.args.StandardRestore(_abstract(like)))
        # uncommitted default-device arrays, like the outputs of `init` and `train_step`, so the
        # next call of a jitted function hits its compilation cache
        stored = jax.tree_util.tree_map(lambda x: jnp.asarray(np.asarray(x)), stored)
        return from_storable(stored, like)

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def save_state(run_dir: str, step: int, state: Any, keep: int = 2) -> None:
    ck = Checkpointer(run_dir, keep)
    try:
        ck.save(step, state)
    finally:
        ck.close()


def restore_state(run_dir: str, like: Any, step: int | None = None) -> Any:
    ck = Checkpointer(run_dir)
    try:
        return ck.restore(like, step)
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

"""Fixed-capacity ring replay buffers that live on the device.

Layout is time-major: every leaf of ``buf.data`` has shape ``(rows, num_envs, ...)`` with
``rows = capacity // num_envs``. One call of :func:`replay_add` writes one time slice of the
``num_envs`` vmapped environments at row ``buf.ptr`` and advances the pointer (wrapping around,
overwriting the oldest slice). Environments that did not produce a transition this step (waiting,
finished, ...) are written too but marked invalid through the per-env ``valid`` mask, so a column
of the buffer is always the time-ordered trajectory of one environment: hindsight relabelling
(:mod:`dscpp_jax.her`) walks forward along it to find the end of an option segment.

The buffer is generic over pytrees. For TD3+HER store :class:`TrajStep` items; for the dynamics
model any pytree such as ``(obs, action, next_obs)`` works, and the ring is then simply a FIFO of
transitions (use ``num_envs`` = the number of transitions added per call, or
:func:`replay_add_many` to add a time-major chunk at once).

Sampling (:func:`replay_sample`) is uniform over valid entries. All functions are pure and
jit-able; sizes are static (they come from the leaves' shapes).
"""
from __future__ import annotations

from typing import Any, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp

PyTree = Any


@flax.struct.dataclass
class TrajStep:
    """One stored step of a goal-conditioned rollout (per env; batch dims in front).

    ``seg_id`` identifies the option segment (int32 per env, incremented whenever a new option
    segment starts in that env); hindsight relabelling never crosses a change of ``seg_id``.
    ``option`` (int32 per env) is the option that ran, stored only where every option learns its
    own TD3 (``Config.per_option_td3``); None (no leaf) otherwise. One segment is one option.
    """

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    goal: jax.Array
    seg_id: jax.Array
    option: Optional[jax.Array] = None


@flax.struct.dataclass
class RegionStep(TrajStep):
    """A :class:`TrajStep` with what the region policies of the baseline DSC
    (``Config.option_policies == "region"``) learn from, as the rollout judged it with the
    classifiers of that iteration: ``in_target`` (bool), ``next_obs`` lies in the running
    option's target region (its option reward: 0 and done there, else -1), and ``at_goal``
    (bool), ``next_obs`` lies in the task's goal region (the global option's reward for every
    transition). (A type of its own, so that the replays of the other learners, and their
    checkpoints, keep TrajStep's fields.)"""

    in_target: Optional[jax.Array] = None
    at_goal: Optional[jax.Array] = None


@flax.struct.dataclass
class Transition:
    """A learning batch for goal-conditioned TD3.

    ``discount`` is the continuation flag in {0, 1}: 0 only when ``next_obs`` reached ``goal``
    (time-outs bootstrap); the learner multiplies it by its discount factor gamma.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    goal: jax.Array
    discount: jax.Array


@flax.struct.dataclass
class Replay:
    """Ring buffer state. ``data`` leaves: ``(rows, num_envs, ...)``; ``valid``: ``(rows, num_envs)``.

    ``ptr`` is the next row to write; ``rows_written`` counts every row ever written (int32), so
    ``min(rows_written, rows)`` rows hold data.
    """

    data: PyTree
    valid: jax.Array
    ptr: jax.Array
    rows_written: jax.Array

    @property
    def rows(self) -> int:
        return self.valid.shape[0]

    @property
    def num_envs(self) -> int:
        return self.valid.shape[1]

    @property
    def capacity(self) -> int:
        return self.valid.shape[0] * self.valid.shape[1]


def replay_init(example: PyTree, capacity: int, num_envs: int) -> Replay:
    """An empty buffer for items shaped like ``example`` (one env's item, no batch dims).

    ``capacity`` is the total number of items; it is rounded down to a multiple of ``num_envs``
    (``rows = capacity // num_envs`` time slices). Storage is zero-initialised.
    """
    capacity = int(capacity)
    num_envs = int(num_envs)
    if num_envs < 1:
        raise ValueError(f"replay_init: num_envs must be >= 1, got {num_envs}")
    if capacity < num_envs:
        raise ValueError(
            f"replay_init: capacity ({capacity}) must be at least num_envs ({num_envs}); "
            "raise the replay capacity in the config"
        )
    rows = capacity // num_envs

    def alloc(x):
        x = jnp.asarray(x)
        return jnp.zeros((rows, num_envs) + x.shape, x.dtype)

    return Replay(
        data=jax.tree_util.tree_map(alloc, example),
        valid=jnp.zeros((rows, num_envs), bool),
        ptr=jnp.zeros((), jnp.int32),
        rows_written=jnp.zeros((), jnp.int32),
    )


def _check_leading(buf: Replay, items: PyTree, lead: Tuple[int, ...], what: str) -> None:
    if jax.tree_util.tree_structure(buf.data) != jax.tree_util.tree_structure(items):
        raise ValueError(f"{what}: item pytree structure differs from the buffer's example")
    for (path, d), x in zip(
        jax.tree_util.tree_flatten_with_path(buf.data)[0], jax.tree_util.tree_leaves(items)
    ):
        want = lead + d.shape[2:]
        if tuple(jnp.shape(x)) != want:
            raise ValueError(
                f"{what}: leaf {jax.tree_util.keystr(path)} has shape {tuple(jnp.shape(x))}, "
                f"expected {want} (buffer was built for num_envs={buf.num_envs})"
            )


def replay_add(buf: Replay, batch_t: PyTree, valid: Optional[jax.Array] = None) -> Replay:
    """Write one time slice (leaves ``(num_envs, ...)``) at ``buf.ptr``; ``valid``: ``(num_envs,)``."""
    b = buf.num_envs
    _check_leading(buf, batch_t, (b,), "replay_add")
    if valid is None:
        valid = jnp.ones((b,), bool)
    valid = jnp.asarray(valid, bool)
    if valid.shape != (b,):
        raise ValueError(f"replay_add: valid has shape {valid.shape}, expected ({b},)")
    row = buf.ptr
    data = jax.tree_util.tree_map(
        lambda d, x: jax.lax.dynamic_update_index_in_dim(d, jnp.asarray(x, d.dtype), row, 0),
        buf.data,
        batch_t,
    )
    return buf.replace(
        data=data,
        valid=jax.lax.dynamic_update_index_in_dim(buf.valid, valid, row, 0),
        ptr=(row + 1) % buf.rows,
        rows_written=buf.rows_written + 1,
    )


def replay_add_many(buf: Replay, batch_tb: PyTree, valid_tb: Optional[jax.Array] = None) -> Replay:
    """Write ``T`` consecutive time slices (leaves ``(T, num_envs, ...)``, ``T <= rows``) at once.

    Equivalent to ``T`` calls of :func:`replay_add` in order.
    """
    leaves = jax.tree_util.tree_leaves(batch_tb)
    if not leaves:
        raise ValueError("replay_add_many: empty item pytree")
    t = leaves[0].shape[0]
    if t > buf.rows:
        raise ValueError(
            f"replay_add_many: chunk of {t} time slices exceeds the buffer's {buf.rows} rows; "
            "add it in pieces or raise the capacity"
        )
    _check_leading(buf, batch_tb, (t, buf.num_envs), "replay_add_many")
    if valid_tb is None:
        valid_tb = jnp.ones((t, buf.num_envs), bool)
    valid_tb = jnp.asarray(valid_tb, bool)
    if valid_tb.shape != (t, buf.num_envs):
        raise ValueError(
            f"replay_add_many: valid has shape {valid_tb.shape}, expected {(t, buf.num_envs)}"
        )
    rows = (buf.ptr + jnp.arange(t, dtype=jnp.int32)) % buf.rows  # distinct since t <= rows
    data = jax.tree_util.tree_map(
        lambda d, x: d.at[rows].set(jnp.asarray(x, d.dtype), unique_indices=True), buf.data, batch_tb
    )
    return buf.replace(
        data=data,
        valid=buf.valid.at[rows].set(valid_tb, unique_indices=True),
        ptr=(buf.ptr + t) % buf.rows,
        rows_written=buf.rows_written + t,
    )


def replay_size(buf: Replay) -> jax.Array:
    """Number of valid items currently stored (int32 scalar)."""
    return jnp.sum(buf.valid, dtype=jnp.int32)


def valid_positions(mask: jax.Array) -> Tuple[jax.Array, jax.Array]:
    """``(positions, size)`` of a 1-D bool ``mask``: ``positions[k]`` is the index of its ``k``-th
    True entry (``(n,)`` int32; the slots from ``size`` on hold ``n - 1``), ``size`` their number.

    Drawing ``k`` uniformly in ``[0, size)`` and looking up ``positions[k]`` samples the True
    entries uniformly with one gather per draw. This is the inverse-CDF draw
    (``searchsorted(cumsum(mask), k, side="right")``) with the search done once for all draws:
    the same indices, without a sequential binary search per draw (which on a GPU is a loop of
    about log2(n) tiny steps inside every sampling step)."""
    mask = jnp.asarray(mask, bool)
    n = mask.shape[0]
    counts = jnp.cumsum(mask, dtype=jnp.int32)
    slot = jnp.arange(n, dtype=jnp.int32)
    # each True entry goes to its rank; the others to distinct out-of-range slots (dropped)
    target = jnp.where(mask, counts - 1, n + slot)
    positions = jnp.full((n,), n - 1, jnp.int32).at[target].set(slot, mode="drop",
                                                                unique_indices=True)
    return positions, counts[-1]


def replay_valid_positions(buf: Replay) -> Tuple[jax.Array, jax.Array]:
    """:func:`valid_positions` of the valid entries in row-major (row, env) order: what
    :func:`replay_sample_index` looks up (compute it once for many draws from one buffer)."""
    return valid_positions(buf.valid.reshape(-1))


def replay_sample_index(buf: Replay, key: jax.Array, n: int,
                        positions: Optional[Tuple[jax.Array, jax.Array]] = None
                        ) -> Tuple[jax.Array, jax.Array]:
    """``n`` (row, env) indices drawn uniformly, with replacement, from the valid entries.

    Exact: the k-th valid entry (k uniform in [0, size)) is looked up in ``positions``
    (:func:`replay_valid_positions` of ``buf``, computed here if not given). On an empty buffer
    every index is the last slot; check :func:`replay_size` first.
    """
    table, total = replay_valid_positions(buf) if positions is None else positions
    u = jax.random.randint(key, (n,), 0, jnp.maximum(total, 1), dtype=jnp.int32)
    idx = table[u]
    return idx // buf.num_envs, idx % buf.num_envs


def replay_recent(buf: Replay, num_rows: int) -> jax.Array:
    """``(rows, num_envs)`` bool: the valid entries among the last ``num_rows`` rows written
    (e.g. one iteration's transitions)."""
    age = (buf.ptr - 1 - jnp.arange(buf.rows, dtype=jnp.int32)) % buf.rows   # 0: the newest row
    recent = (age < int(num_rows)) & (age < buf.rows_written)
    return buf.valid & recent[:, None]


@flax.struct.dataclass
class GroupIndex:
    """The valid entries of a replay sorted by group (e.g. by the option that collected them),
    for draws from one group at a time (:func:`replay_group_sample_index`)."""

    order: jax.Array    # (capacity,) int32 flat (row-major) indices, grouped in group order
    start: jax.Array    # (G,) int32 where each group begins in ``order``
    count: jax.Array    # (G,) int32 the group's valid entries


def replay_group_index(buf: Replay, groups: jax.Array, num_groups: int) -> GroupIndex:
    """Sort the valid entries by ``groups`` (int, the ``valid`` shape; values outside
    ``[0, num_groups)`` are left out): one sort, after which every draw from a group is a gather.
    """
    G = int(num_groups)
    g = jnp.where(buf.valid & (groups >= 0) & (groups < G), groups, G).reshape(-1)
    order = jnp.argsort(g, stable=True).astype(jnp.int32)
    count = jnp.bincount(g, length=G + 1)[:G].astype(jnp.int32)
    start = (jnp.cumsum(count) - count).astype(jnp.int32)
    return GroupIndex(order=order, start=start, count=count)


def replay_group_sample_index(buf: Replay, index: GroupIndex, key: jax.Array, group: jax.Array,
                              n: int) -> Tuple[jax.Array, jax.Array]:
    """``n`` (row, env) indices drawn uniformly, with replacement, from the valid entries of
    group ``group`` (traced). A group without entries gives arbitrary indices: check
    ``index.count`` first."""
    u = jax.random.randint(key, (n,), 0, jnp.maximum(index.count[group], 1), dtype=jnp.int32)
    idx = index.order[jnp.minimum(index.start[group] + u, index.order.shape[0] - 1)]
    return idx // buf.num_envs, idx % buf.num_envs


def replay_gather(buf: Replay, rows: jax.Array, envs: jax.Array) -> PyTree:
    """Items at the given (row, env) index arrays."""
    return jax.tree_util.tree_map(lambda d: d[rows, envs], buf.data)


def replay_sample(buf: Replay, key: jax.Array, n: int) -> PyTree:
    """``n`` items drawn uniformly (with replacement) from the valid entries; leaves ``(n, ...)``."""
    rows, envs = replay_sample_index(buf, key, n)
    return replay_gather(buf, rows, envs)


def replay_flatten(buf: Replay) -> Tuple[PyTree, jax.Array]:
    """All slots as a flat batch: (items with leaves ``(capacity, ...)``, valid mask ``(capacity,)``).

    Handy for statistics such as the dynamics model's normaliser (pass the mask along).
    """
    items = jax.tree_util.tree_map(lambda d: d.reshape((-1,) + d.shape[2:]), buf.data)
    return items, buf.valid.reshape(-1)


def transitions_from_steps(steps: TrajStep, reward: jax.Array, discount: jax.Array) -> Transition:
    """Pack stored steps with given reward / continuation into a :class:`Transition`."""
    return Transition(
        obs=steps.obs,
        action=steps.action,
        reward=reward,
        next_obs=steps.next_obs,
        goal=steps.goal,
        discount=discount,
    )

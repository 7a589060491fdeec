"""Hindsight experience replay (Andrychowicz et al. 2017) as pure batched functions.

Works on a time-major :class:`dscpp_jax.replay.Replay` of :class:`dscpp_jax.replay.TrajStep`
items. An option segment is the contiguous run of valid rows of one env column that share a
``seg_id``; relabelling never leaves it. From a sampled step at row ``r`` the segment is followed
forward for at most ``max_segment`` rows (the option timeout), wrapping around the ring but never
past the newest written row, so a segment that is still running ends at its latest written state.

Strategies (the relabelled goal is an achieved xy, ``next_obs[..., :goal_dim]``):

* ``"final"``: the segment's final achieved xy. The DSC++ authors stored every transition twice,
  with the pursued goal and with this goal: ``relabel_prob=0.5`` samples the same distribution.
* ``"future"``: the achieved xy after a uniformly chosen step ``r + k`` of the same segment,
  ``k`` in ``[0, last]`` (the standard HER "future" strategy).
* ``"none"``: keep the pursued goal.

Reward and continuation are recomputed for the (possibly new) goal: reward 0 within
``goal_tolerance`` of the goal else -1; ``discount`` 0 only when the goal is reached (time-outs and
segment ends bootstrap).

Many draws from one buffer (a learning phase's gradient steps): :func:`her_index` computes, once,
the positions of the valid entries and every entry's distance to its segment's latest step, and
:func:`her_sample` takes the resulting :class:`HERBuffer` in place of the replay. The draws are
the same as from the plain replay; each then costs a few gathers instead of a search of the
buffer's valid mask and of ``max_segment`` rows per sample.
"""
from __future__ import annotations

from typing import Union

import flax.struct
import jax
import jax.numpy as jnp

from dscpp_jax.replay import (Replay, Transition, replay_gather, replay_sample_index,
                              replay_valid_positions)
from dscpp_jax.envs.goals import goal_reached

STRATEGIES = ("final", "future", "none")


def _check(buf: Replay, strategy: str, max_segment: int) -> None:
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown HER strategy {strategy!r}; valid: {list(STRATEGIES)}")
    if int(max_segment) < 1:
        raise ValueError(f"max_segment must be >= 1 (the option timeout), got {max_segment}")
    for field in ("obs", "action", "next_obs", "goal", "seg_id"):
        if not hasattr(buf.data, field):
            raise ValueError(
                f"HER needs a replay of TrajStep items (missing field {field!r}); "
                "build it with replay_init(TrajStep(...), capacity, num_envs)"
            )


@flax.struct.dataclass
class HERBuffer:
    """A replay with what every draw from it needs, computed once by :func:`her_index`."""

    replay: Replay
    positions: jax.Array     # (capacity,) int32: the k-th valid entry's flat index, row-major
    size: jax.Array          # () int32: the number of valid entries
    last_offset: jax.Array   # (rows, num_envs) int32: segment_last_offset of every entry
    max_segment: int = flax.struct.field(pytree_node=False, default=0)


def segment_last_offsets(buf: Replay, max_segment: int) -> jax.Array:
    """:func:`segment_last_offset` of every entry at once, ``(rows, num_envs)`` int32 (0 where
    invalid), in O(rows log rows) work per env column instead of O(max_segment) per entry.

    A step continues into the next row (in write order) when that row is valid, holds the same
    ``seg_id`` and is not past the newest written row; the offset is the number of continuations
    in a row from the entry, capped at ``max_segment - 1`` (and by the ring's length)."""
    n_rows = buf.rows
    window = min(int(max_segment), n_rows)
    # write order, oldest first: position i holds row (ptr + i) % n_rows, the newest last
    seg = jnp.roll(buf.data.seg_id, -buf.ptr, axis=0)
    valid = jnp.roll(buf.valid, -buf.ptr, axis=0)
    cont = jnp.concatenate([(seg[1:] == seg[:-1]) & valid[1:],
                            jnp.zeros((1,) + valid.shape[1:], bool)])  # the newest has no next
    # continuations in a row from position i: (first position j >= i that does not continue) - i,
    # a suffix minimum (associative scan: log-depth, no window-sized reduce)
    pos = jnp.arange(n_rows, dtype=jnp.int32)[:, None]
    stop = jnp.where(cont, n_rows, pos)
    first_stop = jax.lax.associative_scan(jnp.minimum, stop, reverse=True, axis=0)
    run = jnp.where(valid, jnp.minimum(first_stop - pos, window - 1), 0)
    return jnp.roll(run, buf.ptr, axis=0)


def her_index(buf: Replay, max_segment: int) -> HERBuffer:
    """``buf`` with its valid entries' positions and every entry's segment end precomputed,
    for many :func:`her_sample` calls on the same buffer (pass the result in place of ``buf``)."""
    if int(max_segment) < 1:
        raise ValueError(f"max_segment must be >= 1 (the option timeout), got {max_segment}")
    positions, size = replay_valid_positions(buf)
    return HERBuffer(replay=buf, positions=positions, size=size,
                     last_offset=segment_last_offsets(buf, max_segment),
                     max_segment=int(max_segment))


def segment_last_offset(buf: Replay, rows: jax.Array, envs: jax.Array, max_segment: int) -> jax.Array:
    """For each sampled (row, env): how many rows ahead the segment's latest step lies (>= 0)."""
    n_rows = buf.rows
    window = min(int(max_segment), n_rows)
    offs = jnp.arange(window, dtype=jnp.int32)
    latest = (buf.ptr - 1) % n_rows
    age = (latest - rows) % n_rows + 1  # rows written from `rows` up to the newest, in [1, n_rows]
    rr = (rows[:, None] + offs[None, :]) % n_rows  # (n, W), wraps around the ring
    ee = envs[:, None]
    same = (
        (buf.data.seg_id[rr, ee] == buf.data.seg_id[rows, envs][:, None])
        & buf.valid[rr, ee]
        & (offs[None, :] < age[:, None])
    )
    # length of the contiguous prefix of the segment: the first False, or the whole window. (Not
    # sum(cumprod(same)): XLA lowers that cumprod to a window-W reduce-window, W^2 work per sample,
    # and fused into the sum under a seed vmap it took XLA's GPU compiler minutes.)
    run = jnp.where(jnp.all(same, axis=1), window, jnp.argmin(same, axis=1).astype(jnp.int32))
    return jnp.maximum(run - 1, 0)


def her_relabel(
    buf: Union[Replay, HERBuffer],
    rows: jax.Array,
    envs: jax.Array,
    u_future: jax.Array,
    u_relabel: jax.Array,
    strategy: str = "final",
    relabel_prob: float = 0.5,
    max_segment: int = 200,
    goal_tolerance: float = 0.6,
) -> Transition:
    """Deterministic core of :func:`her_sample` given the sampled indices and uniforms in [0, 1).

    ``u_future`` picks the future step (``k = floor(u * (last + 1))``), ``u_relabel < relabel_prob``
    decides which samples get a hindsight goal. Shapes ``(n,)``. ``buf`` may be a
    :class:`HERBuffer` built with the same ``max_segment``.
    """
    index = buf if isinstance(buf, HERBuffer) else None
    if index is not None:
        buf = index.replay
        if index.max_segment != int(max_segment):
            raise ValueError(f"HERBuffer was indexed with max_segment={index.max_segment}, "
                             f"sampled with {max_segment}")
    _check(buf, strategy, max_segment)
    steps = replay_gather(buf, rows, envs)
    goal_dim = steps.goal.shape[-1]
    goal = steps.goal
    if strategy != "none":
        last = (index.last_offset[rows, envs] if index is not None
                else segment_last_offset(buf, rows, envs, max_segment))
        if strategy == "final":
            k = last
        else:
            k = jnp.minimum(jnp.floor(u_future * (last + 1).astype(u_future.dtype)).astype(jnp.int32), last)
        achieved = buf.data.next_obs[(rows + k) % buf.rows, envs][..., :goal_dim]
        relabel = u_relabel < relabel_prob
        goal = jnp.where(relabel[:, None], achieved.astype(goal.dtype), goal)
    reached = goal_reached(steps.next_obs[..., :goal_dim], goal, goal_tolerance)
    return Transition(
        obs=steps.obs,
        action=steps.action,
        reward=jnp.where(reached, 0.0, -1.0).astype(jnp.float32),
        next_obs=steps.next_obs,
        goal=goal,
        discount=1.0 - reached.astype(jnp.float32),
    )


def her_sample(
    key: jax.Array,
    buf: Union[Replay, HERBuffer],
    n: int,
    strategy: str = "final",
    relabel_prob: float = 0.5,
    max_segment: int = 200,
    goal_tolerance: float = 0.6,
) -> Transition:
    """``n`` transitions drawn uniformly from the valid entries, goals relabelled by ``strategy``.

    ``n``, ``strategy`` and ``max_segment`` are static; ``relabel_prob`` and ``goal_tolerance``
    may be traced. ``buf`` may be a :class:`HERBuffer` (:func:`her_index`): the same draws, cheaper.
    """
    replay = buf.replay if isinstance(buf, HERBuffer) else buf
    _check(replay, strategy, max_segment)
    k_idx, k_fut, k_rel = jax.random.split(key, 3)
    rows, envs = replay_sample_index(replay, k_idx, n, (buf.positions, buf.size)
                                     if isinstance(buf, HERBuffer) else None)
    u_future = jax.random.uniform(k_fut, (n,))
    u_relabel = jax.random.uniform(k_rel, (n,))
    return her_relabel(
        buf, rows, envs, u_future, u_relabel, strategy, relabel_prob, max_segment, goal_tolerance
    )


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
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from dscpp_jax.replay import Replay, Transition, replay_gather, replay_sample_index
from envs.goals import goal_reached

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
    buf: Replay,
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
    decides which samples get a hindsight goal. Shapes ``(n,)``.
    """
    _check(buf, strategy, max_segment)
    steps = replay_gather(buf, rows, envs)
    goal_dim = steps.goal.shape[-1]
    goal = steps.goal
    if strategy != "none":
        last = segment_last_offset(buf, rows, envs, max_segment)
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
    buf: Replay,
    n: int,
    strategy: str = "final",
    relabel_prob: float = 0.5,
    max_segment: int = 200,
    goal_tolerance: float = 0.6,
) -> Transition:
    """``n`` transitions drawn uniformly from the valid entries, goals relabelled by ``strategy``.

    ``n``, ``strategy`` and ``max_segment`` are static; ``relabel_prob`` and ``goal_tolerance``
    may be traced.
    """
    _check(buf, strategy, max_segment)
    k_idx, k_fut, k_rel = jax.random.split(key, 3)
    rows, envs = replay_sample_index(buf, k_idx, n)
    u_future = jax.random.uniform(k_fut, (n,))
    u_relabel = jax.random.uniform(k_rel, (n,))
    return her_relabel(
        buf, rows, envs, u_future, u_relabel, strategy, relabel_prob, max_segment, goal_tolerance
    )


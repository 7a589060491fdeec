"""Subgoals for goal-conditioned options: robust sampling and hierarchically optimal DP.

Option ``o`` (a chain link) pursues a goal drawn from its termination region, the pessimistic
initiation region of its parent ``p``. The goal option and the global option pursue the task goal.

Robust sampling (:func:`robust_subgoal`, the paper's Section 3.2 heuristic as the authors' code
did it): shuffle ``p``'s positive trajectories and take the first stored state (the start state
first, then the last ``buffer_len`` positions) whose xy and the four points xy +- tol along each axis
all lie in ``p``'s pessimistic region; else a random positive state of ``p`` inside that region;
else (never for a mature parent with fitted classifiers) a random positive state of ``p``; else the
task goal. Which stored states qualify is cached in the chain by ``options.refit``, so a sample
costs O(P * L) and no classifier evaluation. A uniformly random trajectory among those with a
qualifying state is drawn directly: the same distribution as shuffling and taking the first.

Hierarchical optimality (:func:`dp_value_table`, the paper's Algorithm 1): for every option ``o``
its *input* states are the start states of its positive trajectories; its *output* states are its
parent's input states that lie in the parent's pessimistic region (all of them when none does), and
for the goal option the task goal itself. With a value function ``V(s | g)`` (the shared
goal-conditioned critic)::

    Q_o(s, s') = V(s | s') + gamma * W_p(s'),       W_o(s) = max_{s'} Q_o(s, s'),
    W_goal-option's parent = terminal value of reaching the task goal (0 under 0/-1 rewards),

with ``V(s | s') := 0`` when s and s' are within ``tol`` (already there). The recursion runs from
the goal option outward as a ``lax.fori_loop`` over rows (a parent always has a smaller row index).
The goal option's outputs are valued through the critic as well (``V(s | g)`` plus the terminal
value), so ``W`` measures how far the task goal is along the chain; Algorithm 1's line 13 writes the
goal option's entries as the reward R(s, s'), which would make every continuation equal and reduce
the argmax to "the nearest subgoal".

:func:`pick_subgoal` then chooses ``argmax_{s'} V(s_t | s') + gamma * W_p(s')`` for the current
state (continuation included).

The state the value function sees: inputs are the stored *start observations* of positive
trajectories (``Chain.pos_obs``, ``ChainConfig.obs_dim`` wide; pass ``start_obs`` to
``options.record_outcomes``), goals are xy. ``value_fn(obs (M, obs_dim), goal (M, 2)) -> (M,)`` is a
pure function the caller builds, e.g. ``lambda s, g: td3_value(cfg, td3_state, s, g)``. With
``obs_dim = 2`` the chain stores xy only and ``value_fn`` works on xy. xy is always ``obs[:2]``.
"""
from __future__ import annotations

from typing import Callable, Optional

import jax
import jax.numpy as jnp
from flax import struct

from .options import GLOBAL, GOAL, Chain

NEG = -1e9  # value of invalid table entries

# where robust_subgoal's answer came from
SRC_TASK_GOAL = 0     # goal / global option
SRC_ROBUST = 1        # first state with its neighbourhood inside the parent's pessimistic region
SRC_PESSIMISTIC = 2   # fallback: any positive state inside the parent's pessimistic region
SRC_ANY_POSITIVE = 3  # fallback: any positive state of the parent
SRC_NO_DATA = 4       # fallback: the parent has no positives -> task goal


def _random_true(key, mask):
    """Index of a uniformly random True entry of a flat bool mask (arbitrary when none)."""
    u = jax.random.uniform(key, mask.shape)
    return jnp.argmax(jnp.where(mask, u, -1.0))


def robust_subgoal_with_source(key, chain: Chain, option):
    """Like :func:`robust_subgoal`, also returning where the subgoal came from (SRC_* code)."""
    cfg = chain.cfg
    P, L = cfg.max_pos_traj, cfg.traj_len
    option = jnp.asarray(option, jnp.int32)
    p = jnp.clip(chain.parent[option], 0)
    k_traj, k_pess, k_any = jax.random.split(key, 3)
    xy = chain.pos_xy[p]                                   # (P, L, 2)
    robust = chain.robust_ok[p]                            # (P, L)
    pess = chain.pess_ok[p]
    valid = chain.pos_mask[p]
    # "the first trajectory of a shuffled list that has a qualifying state" is a uniformly random
    # trajectory among those that have one: draw it directly (O(P), no sort); then its first
    # qualifying state (start state first)
    t = _random_true(k_traj, robust.any(axis=1))
    robust_xy = xy[t, jnp.argmax(robust[t])]
    pess_xy = xy.reshape(P * L, 2)[_random_true(k_pess, pess.reshape(-1))]
    any_xy = xy.reshape(P * L, 2)[_random_true(k_any, valid.reshape(-1))]
    src = jnp.where(robust.any(), SRC_ROBUST,
                    jnp.where(pess.any(), SRC_PESSIMISTIC,
                              jnp.where(valid.any(), SRC_ANY_POSITIVE, SRC_NO_DATA)))
    is_link = (option > GOAL) & (chain.parent[option] >= 0)
    src = jnp.where(is_link, src, SRC_TASK_GOAL)
    out = jnp.select([src == SRC_ROBUST, src == SRC_PESSIMISTIC, src == SRC_ANY_POSITIVE],
                     [robust_xy, pess_xy, any_xy], chain.goal_xy)
    return out, src.astype(jnp.int32)


def robust_subgoal(key, chain: Chain, option) -> jax.Array:
    """(2,) subgoal for ``option`` (int) by robust sampling from its parent's positive examples;
    the task goal for the goal and the global option. vmap over envs (keys and options)."""
    return robust_subgoal_with_source(key, chain, option)[0]


# ------------------------------------------------------------------------------------------------
# Hierarchically optimal subgoals (Algorithm 1)
# ------------------------------------------------------------------------------------------------

@struct.dataclass
class DPTable:
    """Algorithm 1's value table, refreshed once per learning iteration. K options, P = max_pos_traj.

    in_xy / in_mask:   (K, P, 2) / (K, P) each option's input states (positive start states).
    out_xy / out_mask: (K, P, 2) / (K, P) each option's output states (candidate subgoals).
    cont:              (K, P) continuation value W_parent(s') at each output (goal option: terminal).
    q:                 (K, P, P) Q_o(s, s') over inputs x outputs (NEG where invalid).
    w:                 (K, P) W_o(s) = max_{s'} Q_o(s, s') per input (NEG where invalid).
    gamma, tol:        () the discount and the "same state" radius the table was built with.
    """

    in_xy: jax.Array
    in_mask: jax.Array
    out_xy: jax.Array
    out_mask: jax.Array
    cont: jax.Array
    q: jax.Array
    w: jax.Array
    gamma: jax.Array
    tol: jax.Array


def _near(a, b, tol):
    return jnp.sum((a - b) ** 2, axis=-1) <= tol * tol


def dp_outputs(chain: Chain, require_pessimistic: bool = True):
    """(out_xy (K, P, 2), out_mask (K, P)): each option's candidate subgoals.

    Chain links: the parent's input states (start states of its positive trajectories), restricted
    to those inside the parent's pessimistic region when ``require_pessimistic`` and any is. Goal
    and global option: the task goal in slot 0."""
    cfg = chain.cfg
    K, P = cfg.max_options, cfg.max_pos_traj
    idx = jnp.arange(K)
    in_xy = chain.pos_xy[:, :, 0]
    in_mask = chain.pos_mask[:, :, 0]
    par = jnp.clip(chain.parent, 0)
    out_xy = in_xy[par]
    out_mask = in_mask[par]
    if require_pessimistic:
        strict = out_mask & chain.pess_ok[par, :, 0]
        out_mask = jnp.where(strict.any(axis=1, keepdims=True), strict, out_mask)
    is_link = (idx > GOAL)[:, None] & (chain.parent >= 0)[:, None] & chain.active[:, None]
    goal_slot = jnp.zeros((K, P), bool).at[:, 0].set(True)
    out_mask = jnp.where(is_link, out_mask, goal_slot & chain.active[:, None])
    out_xy = jnp.where(is_link[..., None], out_xy, chain.goal_xy)
    return out_xy, out_mask


def dp_value_table(chain: Chain, value_fn: Optional[Callable], gamma: float = 0.95, tol=None,
                   goal_value: float = 0.0, require_pessimistic: bool = True,
                   option_value_fn: Optional[Callable] = None) -> DPTable:
    """Algorithm 1 over the whole chain at once: V for all options x inputs x outputs in one
    ``value_fn`` call (K * P * P pairs), then the recursion from the goal option outward.

    value_fn(obs (M, obs_dim), goal (M, 2)) -> (M,) values; gamma: discount of the continuation;
    tol: same-state radius (default ``subgoal_tolerance``); goal_value: value of having reached the
    task goal (terminal). Jit-able; value_fn is a closure (not traced data).
    option_value_fn(option (), obs (M, obs_dim), goal (M, 2)) -> (M,), given instead of
    ``value_fn``: each option's values come from its own value function (one critic per option),
    vmapped over the K options with M = P * P."""
    cfg = chain.cfg
    K, P, D = cfg.max_options, cfg.max_pos_traj, cfg.obs_dim
    tol = cfg.subgoal_tolerance if tol is None else tol
    idx = jnp.arange(K)
    in_xy = chain.pos_xy[:, :, 0]                                          # (K, P, 2)
    in_mask = chain.pos_mask[:, :, 0] & chain.active[:, None] & (idx != GLOBAL)[:, None]
    out_xy, out_mask = dp_outputs(chain, require_pessimistic)
    obs = jnp.broadcast_to(chain.pos_obs[:, :, None, :], (K, P, P, D)).reshape(-1, D)
    goals = jnp.broadcast_to(out_xy[:, None, :, :], (K, P, P, 2)).reshape(-1, 2)
    if (value_fn is None) == (option_value_fn is None):
        raise ValueError("dp_value_table: pass exactly one of value_fn and option_value_fn")
    if option_value_fn is None:
        v = jnp.asarray(value_fn(obs, goals), jnp.float32).reshape(K, P, P)
    else:
        v = jax.vmap(option_value_fn)(jnp.arange(K, dtype=jnp.int32), obs.reshape(K, P * P, D),
                                      goals.reshape(K, P * P, 2))
        v = jnp.asarray(v, jnp.float32).reshape(K, P, P)
    v = jnp.where(_near(in_xy[:, :, None, :], out_xy[:, None, :, :], tol), 0.0, v)
    pair_mask = in_mask[:, :, None] & out_mask[:, None, :]
    gamma = jnp.asarray(gamma, jnp.float32)

    def cont_of(k, w):
        return jnp.where(k == GOAL, jnp.full((P,), goal_value, jnp.float32), w[jnp.clip(chain.parent[k], 0)])

    def body(k, w):
        qk = jnp.where(pair_mask[k], v[k] + gamma * cont_of(k, w)[None, :], NEG)
        wk = jnp.max(qk, axis=1)
        wk = jnp.where(in_mask[k] & (wk > NEG / 2), wk, NEG)
        return w.at[k].set(wk)

    w = jax.lax.fori_loop(GOAL, K, body, jnp.full((K, P), NEG, jnp.float32))
    cont = jax.vmap(lambda k: cont_of(k, w))(idx)                          # (K, P)
    q = jnp.where(pair_mask, v + gamma * cont[:, None, :], NEG)
    q = jnp.where(q > NEG / 2, q, NEG)
    return DPTable(in_xy=in_xy, in_mask=in_mask, out_xy=out_xy, out_mask=out_mask,
                   cont=jnp.where(out_mask, cont, NEG), q=q, w=w, gamma=gamma,
                   tol=jnp.asarray(tol, jnp.float32))


def dp_table_init(chain: Chain) -> DPTable:
    """An empty table with the right shapes (every entry invalid): picks fall back to the goal."""
    cfg = chain.cfg
    K, P = cfg.max_options, cfg.max_pos_traj
    f = jnp.full((K, P), NEG, jnp.float32)
    z2 = jnp.zeros((K, P, 2), jnp.float32)
    zb = jnp.zeros((K, P), bool)
    return DPTable(in_xy=z2, in_mask=zb, out_xy=z2, out_mask=zb, cont=f,
                   q=jnp.full((K, P, P), NEG, jnp.float32), w=f,
                   gamma=jnp.asarray(0.95, jnp.float32),
                   tol=jnp.asarray(cfg.subgoal_tolerance, jnp.float32))


def subgoal_scores(table: DPTable, option, obs, value_fn: Callable) -> jax.Array:
    """(P,) Q(s_t, s') = V(s_t | s') + gamma * W_parent(s') over the option's outputs (NEG where
    invalid). obs: (obs_dim,) current observation, xy = obs[:2]."""
    obs = jnp.asarray(obs, jnp.float32)
    option = jnp.asarray(option, jnp.int32)
    outs = table.out_xy[option]
    P = outs.shape[0]
    v = jnp.asarray(value_fn(jnp.broadcast_to(obs, (P,) + obs.shape), outs), jnp.float32)
    v = jnp.where(_near(obs[:2], outs, table.tol), 0.0, v)
    return jnp.where(table.out_mask[option], v + table.gamma * table.cont[option], NEG)


def pick_subgoal(table: DPTable, chain: Chain, option, obs, value_fn: Callable) -> jax.Array:
    """(2,) the hierarchically optimal subgoal for ``option`` from the current observation ``obs``
    (obs_dim,) (the continuation included). The goal and the global option, and options without
    any valid output, get the task goal. vmap over envs."""
    option = jnp.asarray(option, jnp.int32)
    s = subgoal_scores(table, option, obs, value_fn)
    j = jnp.argmax(s)
    ok = (option > GOAL) & table.out_mask[option].any()
    return jnp.where(ok, table.out_xy[option, j], chain.goal_xy)

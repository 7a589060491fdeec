"""The chain's frontier: free space next to an option's region that no mature option covers yet.

Beyond the paper (both uses are off by default and on in the ant ``fast`` preset where they were
measured to pay: DSC++'s skill chains on the mazes with dead ends and on four rooms, never the
paper's baselines, ``config.FRONTIER_CHAINS``; ``docs/presets.md``, "The chain's frontier").
The paper grows a linear chain: each new option targets the newest mature one, and learns its
initiation region from wherever its executions happen to succeed. With diverse starts spread
uniformly over the maze, that is where most free space lies, so at a junction the chain can turn
into a dead end; once it has filled the dead end, the option in gestation finds no uncovered state
within reach of its target and the chain stops (``experiments/results/README.md``, medium maze). Two uses
of one probe address that:

- **frontier starts** (``Config.frontier.start_prob``): a share of the training episodes starts in
  uncovered free space within ``frontier.radius`` of the region of the option that the option in
  gestation targets (and at least ``frontier.inner_radius`` from it), where that option's
  executions can succeed (a reverse curriculum over the chain); with ``frontier.goal_starts``
  also for the goal option, next to the task goal (:func:`goal_pool`);
- **frontier parents** (``Config.frontier.parent``): a new option targets the newest mature option
  whose frontier is still open, and an option in gestation whose target's frontier has closed (a
  filled dead end) is re-targeted there, its examples cleared. The chain becomes a tree whose
  branches end in dead ends; the policy over options still walks the rows in increasing index
  (every parent is older than its child).

The probe is a Monte Carlo estimate from candidate states drawn by the env's diverse-start sampler
(uniform over free space, the same knowledge diverse starts already use): candidate ``m`` is on the
frontier of row ``k`` when no mature option's initiation set (optimistic OR pessimistic) holds it
and it lies within ``radius`` of one of row ``k``'s positive states inside ``k``'s pessimistic region
(the states its children draw subgoals from). Pure and shape-stable: candidates (M, 2) in, (K, M)
out; vmap over seeds. :func:`grow_chain` is ``options.grow_chain`` with the frontier's parents.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from dscpp_jax.options import GESTATION, GOAL, MATURE, Chain, add_option, check_start, classify_all, \
    clear_row, mature_options


def _checked_candidates(caller: str, cand_xy, radius: float, inner: float) -> jax.Array:
    """``cand_xy`` as a float32 (M, 2) array, with the radii checked (ValueError naming `caller`)."""
    cand = jnp.asarray(cand_xy, jnp.float32)
    if cand.ndim != 2 or cand.shape[-1] != 2:
        raise ValueError(f"{caller}: cand_xy must have shape (M, 2), got {cand.shape}")
    if not float(radius) > 0 or not 0 <= float(inner) < float(radius):
        raise ValueError(f"{caller}: need 0 <= inner < radius, got inner={inner}, "
                         f"radius={radius}")
    return cand


def frontier_probe(chain: Chain, cand_xy, radius: float, inner: float = 0.0) -> jax.Array:
    """(K, M) bool: candidate m (``cand_xy`` (M, 2)) is uncovered free space within ``radius`` of
    mature row k's positive states inside k's pessimistic region, and no nearer than ``inner`` to
    any of them (False for other rows)."""
    cand = _checked_candidates("frontier_probe", cand_xy, radius, inner)
    mature = chain.status == MATURE
    ini = jax.vmap(lambda p: classify_all(chain, p)[0])(cand)            # (M, K)
    uncovered = ~jnp.any(ini & mature[None, :], axis=1)                     # (M,)
    K, P, L = chain.pos_xy.shape[:3]
    r2, i2 = float(radius) ** 2, float(inner) ** 2

    def row_near(args):
        xy, ok = args                                                       # (P, L, 2), (P, L)
        d2 = jnp.sum((cand[:, None, :] - xy.reshape(P * L, 2)[None]) ** 2, axis=-1)
        d2 = jnp.min(jnp.where(ok.reshape(P * L)[None, :], d2, jnp.inf), axis=1)   # (M,)
        return (d2 <= r2) & (d2 >= i2)

    near = jax.lax.map(row_near, (chain.pos_xy, chain.pess_ok))            # (K, M)
    return near & uncovered[None, :] & mature[:, None]


def open_rows(probe: jax.Array, min_count: int) -> jax.Array:
    """(K,) bool: rows with at least ``min_count`` frontier candidates (an open frontier)."""
    return jnp.sum(probe, axis=1) >= min_count


def gestation_row(chain: Chain) -> jax.Array:
    """int32 row of the chain link in gestation (at most one), -1 when none."""
    idx = jnp.arange(chain.cfg.max_options)
    gest = (chain.status == GESTATION) & (idx > GOAL)
    return jnp.where(gest.any(), jnp.argmax(gest), -1).astype(jnp.int32)


def start_pool(chain: Chain, probe: jax.Array) -> jax.Array:
    """(M,) bool: the frontier of the row that the link in gestation targets (all False when no
    link is in gestation): where frontier starts are drawn from."""
    g = gestation_row(chain)
    p = chain.parent[jnp.clip(g, 0)]
    return probe[jnp.clip(p, 0)] & (g >= 0) & (p >= 0)


def goal_pool(chain: Chain, cand_xy, radius: float, inner: float = 0.0) -> jax.Array:
    """(M,) bool: while the goal option is in gestation, candidate m (``cand_xy`` (M, 2)) lies
    within ``radius`` of the task goal and no nearer than ``inner`` to it (all False otherwise):
    the goal option's frontier starts (``Config.frontier.goal_starts``). Before the goal option
    matures no row has examples inside a pessimistic region, so :func:`start_pool` is empty."""
    cand = _checked_candidates("goal_pool", cand_xy, radius, inner)
    d2 = jnp.sum((cand - chain.goal_xy[None, :]) ** 2, axis=-1)
    near = (d2 <= float(radius) ** 2) & (d2 >= float(inner) ** 2)
    return near & (chain.status[GOAL] == GESTATION)


def frontier_parent(chain: Chain, is_open: jax.Array) -> jax.Array:
    """int32: the newest mature row with an open frontier; the newest mature row when none is
    open; -1 when no row is mature."""
    idx = jnp.arange(chain.cfg.max_options)
    mature = chain.status == MATURE
    newest = jnp.max(jnp.where(mature, idx, -1))
    newest_open = jnp.max(jnp.where(mature & is_open, idx, -1))
    return jnp.where(newest_open >= 0, newest_open, newest).astype(jnp.int32)


def grow_chain(chain: Chain, start_xy, is_open: jax.Array) -> Chain:
    """``options.grow_chain`` with the frontier's parents (call after ``options.refit``).

    ``is_open``: (K,) bool, which rows have an open frontier (:func:`open_rows`), measured on the
    chain after its maturity step (``options.mature_options``). Options in gestation with enough
    successes become mature; a link in gestation whose parent's frontier has closed is
    re-targeted to the newest mature option with an open frontier, its examples cleared
    (``options.clear_row``); then, as in the paper, a new option is created while no mature
    option's initiation set holds ``start_xy``, its parent the newest mature option with an open
    frontier (the newest mature one when none is open; ``options.add_option``)."""
    start_xy = check_start(start_xy)
    chain = mature_options(chain)
    is_open = jnp.asarray(is_open, bool)
    newest = frontier_parent(chain, is_open)
    g = gestation_row(chain)
    gc = jnp.clip(g, 0)
    p = chain.parent[gc]
    switch = ((g >= 0) & (p >= 0) & ~is_open[jnp.clip(p, 0)] & (newest >= 0)
              & is_open[jnp.clip(newest, 0)] & (newest != p))
    chain = clear_row(chain, g, switch)
    chain = chain.replace(parent=chain.parent.at[gc].set(jnp.where(switch, newest, p)))
    return add_option(chain, newest, start_xy)

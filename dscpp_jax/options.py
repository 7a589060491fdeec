"""The skill chain: a fixed-capacity option table that lives on the device.

Rows of the table (``K = ChainConfig.max_options``):

- row 0, the *global option*: initiation everywhere, targets the task goal. It only keeps success /
  execution counters: it stores no examples and never gets classifiers (its initiation set is the
  whole state space by definition, and no option targets it).
- row 1, the *goal option*: targets the task goal; the first link of the chain.
- rows 2.., chain links in creation order. Row ``k`` targets its parent (``parent[k] = k - 1`` in
  the paper's linear chain; an older row when :mod:`dscpp_jax.frontier` picks parents): it
  terminates inside the parent's pessimistic initiation region. Because links are created one at a
  time, a parent always has a smaller index than its child, so "walk the chain from the goal option
  outward" is "walk the rows in increasing index".

Each row has a status (``FREE``, ``GESTATION``, ``MATURE``; the global option is ``ALWAYS``),
success / execution counters, a ring of positive trajectories (start state + the last
``buffer_len`` visited xy positions of a successful execution, with a validity mask), a ring of
negative start states (failed executions), its fitted initiation classifiers (from
:mod:`dscpp_jax.initiation`, stacked over rows), and a cache used by robust subgoal sampling (which
stored positive states lie, with their +-subgoal_tolerance neighbourhood, inside the row's own
pessimistic region; refreshed by :func:`refit`).

Per environment step (inside ``lax.scan``; single-env functions are vmapped over the B envs)::

    o     = select_option(chain, xy)                          # () int32 per env
    g     = subgoals.robust_subgoal(key, chain, o)            # (2,) per env; or, with a DP table,
          # subgoals.pick_subgoal(table, chain, o, obs, value_fn)
    ... act towards g, step the env, append xy to the env's last-buffer_len ring ...
    ok    = local_success(chain, o, next_xy, g)               # () bool per env
    ended = ok | timeout (option_timeout) | episode end
    chain = record_outcomes(chain, o_ids, ok, start_xy, traj_xy, traj_mask, ended,
                            start_obs)                        # batched (B,), training only

Per learning iteration (after the scan)::

    chain = refit(chain)                      # rows that got examples (vmapped SMO over rows)
    chain = grow_chain(chain, env.start)      # maturity, then at most one new option
    table = subgoals.dp_value_table(chain, value_fn)   # DP subgoals only
    metrics = chain_metrics(chain, env.start)

All functions are pure, jit-able and shape-stable; the config is a static field of :class:`Chain`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Optional

import jax
import jax.numpy as jnp
from flax import struct

from dscpp_jax import initiation, svm
from dscpp_jax.config import ChainSection

FREE = 0
GESTATION = 1
MATURE = 2
ALWAYS = 3  # status of the global option
STATUS_NAMES = ("free", "gestation", "mature", "always")   # by status value

GLOBAL = 0
GOAL = 1

VARIANTS = ("dual", "single")


@dataclass(frozen=True)
class ChainConfig:
    """Static sizes and constants of the skill chain (frozen, hashable: a jit static)."""

    max_options: int = 12        # capacity K, including the global and the goal option
    gestation: int = 10          # successes before an option is mature
    initiation_period: int = 0   # further successes of the newest mature option before its child
    buffer_len: int = 50         # positions kept after the start state of a positive trajectory
    option_timeout: int = 200    # steps before an execution counts as a failure (used by callers)
    max_pos_traj: int = 100      # positive trajectories kept per option (ring)
    max_neg: int = 100           # negative start states kept per option (ring)
    variant: str = "dual"        # "dual" (optimistic + pessimistic) | "single" (baseline DSC)
    goal_tolerance: float = 0.6  # radius of the task goal region
    subgoal_tolerance: float = 0.6  # radius of a sampled subgoal; also the robust neighbourhood
    obs_dim: int = 2             # size of the stored start observation of each positive trajectory
    svm_gamma: float = 0.5       # RBF gamma ("auto" for x, y features)
    svm_C: float = 1.0
    nu_pessimistic: float = 0.1
    nu_optimistic: float = 0.01
    balanced_min_neg: int = 10   # class_weight "balanced" from this many negatives on
    svm_tol: float = 1e-3
    svm_max_iter: Optional[int] = None
    svm_backend: str = "auto"    # "auto" (fused SMO kernel on GPUs, XLA loop elsewhere) | "xla" | "pallas"

    def __post_init__(self):
        def need(ok, msg):
            if not ok:
                raise ValueError(f"ChainConfig: {msg}")

        need(self.max_options >= 3, f"max_options={self.max_options} must be >= 3 (global option, "
             "goal option and at least one chain link)")
        need(self.gestation >= 1, f"gestation={self.gestation} must be >= 1")
        need(self.initiation_period >= 0,
             f"initiation_period={self.initiation_period} must be >= 0 (0: a child as soon as its "
             "parent is mature)")
        need(self.buffer_len >= 1, f"buffer_len={self.buffer_len} must be >= 1")
        need(self.option_timeout >= 1, f"option_timeout={self.option_timeout} must be >= 1")
        need(self.max_pos_traj >= 1, f"max_pos_traj={self.max_pos_traj} must be >= 1")
        need(self.max_neg >= 1, f"max_neg={self.max_neg} must be >= 1")
        need(self.variant in VARIANTS, f"variant={self.variant!r} must be one of {VARIANTS}")
        need(self.goal_tolerance > 0, "goal_tolerance must be > 0")
        need(self.subgoal_tolerance > 0, "subgoal_tolerance must be > 0")
        need(self.obs_dim >= 2, f"obs_dim={self.obs_dim} must be >= 2 (xy = obs[:2])")
        need(self.svm_gamma > 0, "svm_gamma must be > 0")
        need(0 < self.nu_pessimistic <= 1 and 0 < self.nu_optimistic <= 1, "nu must be in (0, 1]")
        need(self.svm_backend in ("auto", "xla", "pallas"),
             f"svm_backend={self.svm_backend!r} must be 'auto', 'xla' or 'pallas'")

    @property
    def traj_len(self) -> int:
        """Stored states per positive trajectory: the start state + ``buffer_len`` positions."""
        return self.buffer_len + 1

    def replace(self, **kw: Any) -> "ChainConfig":
        return dataclasses.replace(self, **kw)

    @classmethod
    def from_section(cls, section: ChainSection, *, variant: str, initiation_period: int,
                     goal_tolerance: float, obs_dim: int) -> "ChainConfig":
        """The skill chain a run config's `chain` section sets, with what the run's other
        settings decide: the classifier `variant`, the `initiation_period` in effect, the goal
        tolerance (also the subgoals') and the env's observation size."""
        return cls(max_options=section.max_options, gestation=section.gestation,
                   initiation_period=initiation_period, buffer_len=section.buffer_len,
                   option_timeout=section.option_timeout, max_pos_traj=section.max_pos_traj,
                   max_neg=section.max_neg, variant=variant, goal_tolerance=goal_tolerance,
                   subgoal_tolerance=goal_tolerance, obs_dim=obs_dim,
                   svm_gamma=section.svm_gamma, svm_backend=section.svm_backend)


@struct.dataclass
class Chain:
    """The option table. Shapes: K options, P = max_pos_traj, L = buffer_len + 1, N = max_neg,
    D = obs_dim."""

    cfg: ChainConfig = struct.field(pytree_node=False)
    goal_xy: jax.Array          # (2,) task goal
    status: jax.Array           # (K,) int32: FREE / GESTATION / MATURE / ALWAYS
    parent: jax.Array           # (K,) int32, -1 for the global and the goal option and free rows
    successes: jax.Array        # (K,) int32 successful executions (training only)
    executions: jax.Array       # (K,) int32 executions
    pos_xy: jax.Array           # (K, P, L, 2) positive trajectories: [:, :, 0] = start state
    pos_mask: jax.Array         # (K, P, L) bool; [:, :, 0] = the trajectory slot is valid
    pos_obs: jax.Array          # (K, P, D) start observation of each positive trajectory
    pos_count: jax.Array        # (K,) int32 positive trajectories ever written (ring head)
    neg_xy: jax.Array           # (K, N, 2) failed start states
    neg_mask: jax.Array         # (K, N) bool
    neg_count: jax.Array        # (K,) int32 negatives ever written
    clf: Any                    # initiation classifiers stacked over K (dscpp_jax.initiation)
    fitted: jax.Array           # (K,) bool: clf row holds a fitted classifier
    dirty: jax.Array            # (K,) bool: new examples since the last refit
    pess_ok: jax.Array          # (K, P, L) bool: positive state inside the row's pessimistic region
    robust_ok: jax.Array        # (K, P, L) bool: ... and its +-tol neighbourhood too
    num_options: jax.Array      # () int32 rows in use (global + goal + links)
    capacity_hit: jax.Array     # () bool: a new option was needed but the table was full

    @property
    def active(self) -> jax.Array:
        """(K,) bool rows in use."""
        return self.status != FREE


# ------------------------------------------------------------------------------------------------
# Classifier adapter (the only place that touches dscpp_jax.initiation)
# ------------------------------------------------------------------------------------------------

def initiation_config(cfg: ChainConfig):
    """The :class:`dscpp_jax.initiation.InitiationConfig` matching a chain config."""
    return initiation.InitiationConfig(
        variant=cfg.variant, gamma=cfg.svm_gamma, C=cfg.svm_C, nu_pessimistic=cfg.nu_pessimistic,
        nu_optimistic=cfg.nu_optimistic, nu_single=cfg.nu_pessimistic,
        balanced_min_negatives=cfg.balanced_min_neg, tol=cfg.svm_tol, max_iter=cfg.svm_max_iter)


def _empty_classifiers(cfg: ChainConfig):
    """Unfitted classifiers over P * L positive + N negative slots, stacked over K rows."""
    one = initiation.empty_initiation(cfg.max_pos_traj * cfg.traj_len, cfg.max_neg, 2,
                                         cfg.svm_gamma)
    return jax.tree_util.tree_map(
        lambda x: jnp.broadcast_to(x, (cfg.max_options,) + x.shape), one)


def _fitted_flags(clf):
    return clf.optimistic_fitted | clf.pessimistic_fitted


def _row(tree, k):
    return jax.tree_util.tree_map(lambda a: a[k], tree)


# ------------------------------------------------------------------------------------------------
# Construction and queries
# ------------------------------------------------------------------------------------------------

def chain_init(cfg: ChainConfig, goal_xy) -> Chain:
    """A chain with the global option (row 0) and the goal option (row 1, in gestation)."""
    if not isinstance(cfg, ChainConfig):
        raise ValueError(f"chain_init: cfg must be a ChainConfig, got {type(cfg).__name__}")
    goal_xy = jnp.asarray(goal_xy, jnp.float32)
    if goal_xy.shape != (2,):
        raise ValueError(f"chain_init: goal_xy must have shape (2,), got {goal_xy.shape}")
    K, P, L, N, D = cfg.max_options, cfg.max_pos_traj, cfg.traj_len, cfg.max_neg, cfg.obs_dim
    status = jnp.full((K,), FREE, jnp.int32).at[GLOBAL].set(ALWAYS).at[GOAL].set(GESTATION)
    zi = jnp.zeros((K,), jnp.int32)
    return Chain(
        cfg=cfg, goal_xy=goal_xy, status=status, parent=jnp.full((K,), -1, jnp.int32),
        successes=zi, executions=zi,
        pos_xy=jnp.zeros((K, P, L, 2), jnp.float32), pos_mask=jnp.zeros((K, P, L), bool),
        pos_obs=jnp.zeros((K, P, D), jnp.float32), pos_count=zi,
        neg_xy=jnp.zeros((K, N, 2), jnp.float32), neg_mask=jnp.zeros((K, N), bool), neg_count=zi,
        clf=_empty_classifiers(cfg), fitted=jnp.zeros((K,), bool), dirty=jnp.zeros((K,), bool),
        pess_ok=jnp.zeros((K, P, L), bool), robust_ok=jnp.zeros((K, P, L), bool),
        num_options=jnp.asarray(2, jnp.int32), capacity_hit=jnp.asarray(False))


def _near(a, b, tol):
    return jnp.sum((a - b) ** 2, axis=-1) <= tol * tol


def classify_all(chain: Chain, xy):
    """(K,) initiation and (K,) pessimistic decisions of every row's classifiers at xy (2,),
    False for rows without a fitted classifier."""
    xy = jnp.asarray(xy, jnp.float32)
    opt = jax.vmap(lambda c: initiation.optimistic_contains(c, xy))(chain.clf)
    pess = jax.vmap(lambda c: initiation.pessimistic_contains(c, xy))(chain.clf)
    return (opt | pess) & chain.fitted, pess & chain.fitted


def can_initiate(chain: Chain, xy) -> jax.Array:
    """(K,) bool: which options may start at xy (2,). The global option and options in gestation
    always; mature options where optimistic OR pessimistic holds; free rows never."""
    ini, _ = classify_all(chain, xy)
    return (chain.status == ALWAYS) | (chain.status == GESTATION) | ((chain.status == MATURE) & ini)


def in_termination_region(chain: Chain, xy, task_goal=None) -> jax.Array:
    """(K,) bool: option_terminates for every row at xy (2,) (one classifier pass)."""
    goal = chain.goal_xy if task_goal is None else jnp.asarray(task_goal, jnp.float32)
    _, pess = classify_all(chain, xy)
    at_goal = _near(jnp.asarray(xy, jnp.float32), goal, chain.cfg.goal_tolerance)
    idx = jnp.arange(chain.cfg.max_options)
    par = jnp.clip(chain.parent, 0)
    by_parent = pess[par] & (chain.parent >= 0)
    return jnp.where(idx <= GOAL, at_goal, by_parent) & chain.active


def option_terminates(chain: Chain, o, xy, task_goal=None) -> jax.Array:
    """bool: option o (int) terminates at xy (2,). Global and goal option: within goal_tolerance
    of the task goal (default ``chain.goal_xy``); chain links: inside the parent's pessimistic
    region."""
    goal = chain.goal_xy if task_goal is None else jnp.asarray(task_goal, jnp.float32)
    xy = jnp.asarray(xy, jnp.float32)
    o = jnp.asarray(o, jnp.int32)
    p = chain.parent[o]
    pc = jnp.clip(p, 0)
    in_parent = initiation.pessimistic_contains(_row(chain.clf, pc), xy) & chain.fitted[pc] & (p >= 0)
    at_goal = _near(xy, goal, chain.cfg.goal_tolerance)
    return jnp.where(o <= GOAL, at_goal, in_parent)


def local_success(chain: Chain, o, xy, subgoal, task_goal=None) -> jax.Array:
    """bool: the option's execution succeeded at xy: within subgoal_tolerance of its subgoal AND in
    its termination region (the original's ``is_at_local_goal``)."""
    xy = jnp.asarray(xy, jnp.float32)
    near = _near(xy, jnp.asarray(subgoal, jnp.float32), chain.cfg.subgoal_tolerance)
    return near & option_terminates(chain, o, xy, task_goal)


def select_option(chain: Chain, xy, at_subgoal=None, prefer_pessimistic: bool = False) -> jax.Array:
    """The policy over options at xy (2,): walk the chain from the goal option outward and take
    the first option that can initiate and is not already done; else the global option (0).

    ``at_subgoal`` (optional, (K,) bool) says which options count as already done (e.g. computed
    with :func:`local_success` against freshly sampled subgoals, as the original did); by default an
    option is done where it already terminates (:func:`in_termination_region`).
    ``prefer_pessimistic``: first walk the chain with the mature options' pessimistic regions alone
    (the stable part of each initiation set) and use the full walk only when none holds xy. The
    optimistic regions exist to explore; between refits one can swell over states its option cannot
    start from, and a policy that trusts it there repeats the same failure (no learning happens
    during evaluation). Off by default (the paper's walk). Returns int32.
    """
    K = chain.cfg.max_options
    ini, pess = classify_all(chain, xy)
    init = (chain.status == GESTATION) | ((chain.status == MATURE) & ini)
    if at_subgoal is None:
        goal = chain.goal_xy
        at_goal = _near(jnp.asarray(xy, jnp.float32), goal, chain.cfg.goal_tolerance)
        par = jnp.clip(chain.parent, 0)
        at_subgoal = jnp.where(jnp.arange(K) <= GOAL, at_goal, pess[par] & (chain.parent >= 0))
    else:
        at_subgoal = jnp.asarray(at_subgoal, bool)
        if at_subgoal.shape != (K,):
            raise ValueError(f"select_option: at_subgoal must have shape ({K},), got "
                             f"{at_subgoal.shape}")
    chain_rows = jnp.arange(K) >= GOAL
    cand = init & ~at_subgoal & chain_rows
    choice = jnp.where(cand.any(), jnp.argmax(cand), GLOBAL)
    if prefer_pessimistic:
        safe = (chain.status == MATURE) & pess & ~at_subgoal & chain_rows
        choice = jnp.where(safe.any(), jnp.argmax(safe), choice)
    return choice.astype(jnp.int32)


# ------------------------------------------------------------------------------------------------
# Recording outcomes (batched over envs)
# ------------------------------------------------------------------------------------------------

def _ring_slots(oid, is_event, count, capacity):
    """Ring write positions for a batch of events, equal to writing them one by one in env order.

    oid: (B,) row per event, is_event: (B,) bool, count: (K,) entries written so far per row.
    Returns (row (B,), slot (B,), n_new (K,)): row = K (out of bounds: drop) for non-events and for
    events that a later event of the same burst overwrites, so no two kept writes share a slot
    (scatter order with duplicate indices is unspecified on accelerators).
    """
    K = count.shape[0]
    onehot = jax.nn.one_hot(oid, K, dtype=jnp.int32) * is_event[:, None]
    c = jnp.cumsum(onehot, axis=0)
    rank = jnp.sum((c - 1) * onehot, axis=1)           # earlier events of the same row
    n_new = c[-1]
    keep = is_event & (rank >= n_new[oid] - capacity)  # only the last `capacity` of a burst
    slot = (count[oid] + rank) % capacity
    return jnp.where(keep, oid, K), slot, n_new


def record_outcomes(chain: Chain, option_ids, success, start_xy, traj_xy, traj_mask, event_mask,
                    start_obs=None) -> Chain:
    """Record the option executions that ended this step in B envs (several may end the same option).

    Args:
      option_ids: (B,) int32 option that ended in each env (ignored where ``event_mask`` is False).
      success: (B,) bool local success of that execution.
      start_xy: (B, 2) xy where the execution started.
      traj_xy: (B, buffer_len, 2) the last ``buffer_len`` visited positions, oldest first.
      traj_mask: (B, buffer_len) bool valid positions (executions shorter than buffer_len).
      event_mask: (B,) bool an execution ended in this env.
      start_obs: (B, obs_dim) start observation (for the DP value table); may be omitted when
        ``obs_dim == 2`` (then ``start_xy`` is stored).

    Every event bumps the option's execution counter; a success also bumps its success counter and
    (except for the global option) writes start + trajectory as one positive trajectory; a failure
    writes its start state as a negative (except for the global option). Events are applied in env
    order, exactly as if recorded one by one; rows that got examples are marked dirty. Events for
    free rows or out-of-range ids are ignored.
    """
    cfg = chain.cfg
    K, P, L, N, D, T = (cfg.max_options, cfg.max_pos_traj, cfg.traj_len, cfg.max_neg, cfg.obs_dim,
                        cfg.buffer_len)
    option_ids = jnp.asarray(option_ids, jnp.int32)
    B = option_ids.shape[0] if option_ids.ndim == 1 else -1
    if option_ids.ndim != 1:
        raise ValueError(f"record_outcomes: option_ids must have shape (B,), got {option_ids.shape}")
    start_xy = jnp.asarray(start_xy, jnp.float32)
    traj_xy = jnp.asarray(traj_xy, jnp.float32)
    traj_mask = jnp.asarray(traj_mask, bool)
    want = {"success": (B,), "start_xy": (B, 2), "traj_xy": (B, T, 2), "traj_mask": (B, T),
            "event_mask": (B,)}
    got = {"success": jnp.shape(success), "start_xy": start_xy.shape, "traj_xy": traj_xy.shape,
           "traj_mask": traj_mask.shape, "event_mask": jnp.shape(event_mask)}
    for name, shape in want.items():
        if tuple(got[name]) != shape:
            raise ValueError(f"record_outcomes: {name} must have shape {shape} (B={B}, "
                             f"buffer_len={T}), got {tuple(got[name])}")
    if start_obs is None:
        if D != 2:
            raise ValueError(f"record_outcomes: start_obs (B, {D}) is required when "
                             f"ChainConfig.obs_dim={D} != 2")
        start_obs = start_xy
    start_obs = jnp.asarray(start_obs, jnp.float32)
    if start_obs.shape != (B, D):
        raise ValueError(f"record_outcomes: start_obs must have shape ({B}, {D}), got "
                         f"{start_obs.shape}")
    success = jnp.asarray(success, bool)
    in_range = (option_ids >= 0) & (option_ids < K)
    oid = jnp.clip(option_ids, 0, K - 1)
    ev = jnp.asarray(event_mask, bool) & in_range & (chain.status[oid] != FREE)
    learns = ev & (oid != GLOBAL)
    onehot_k = jax.nn.one_hot(oid, K, dtype=jnp.int32)
    executions = chain.executions + jnp.sum(onehot_k * ev[:, None], axis=0)
    successes = chain.successes + jnp.sum(onehot_k * (ev & success)[:, None], axis=0)

    # positives: start + last buffer_len positions
    row, slot, n_new = _ring_slots(oid, learns & success, chain.pos_count, P)
    traj = jnp.concatenate([start_xy[:, None, :], traj_xy], axis=1)          # (B, L, 2)
    tmask = jnp.concatenate([jnp.ones((B, 1), bool), traj_mask], axis=1)     # (B, L)
    pos_xy = chain.pos_xy.at[row, slot].set(traj, mode="drop")
    pos_mask = chain.pos_mask.at[row, slot].set(tmask, mode="drop")
    pos_obs = chain.pos_obs.at[row, slot].set(start_obs, mode="drop")
    pess_ok = chain.pess_ok.at[row, slot].set(False, mode="drop")      # stale until the next refit
    robust_ok = chain.robust_ok.at[row, slot].set(False, mode="drop")
    pos_count = chain.pos_count + n_new

    # negatives: the start state of a failed execution
    row_n, slot_n, n_neg = _ring_slots(oid, learns & ~success, chain.neg_count, N)
    neg_xy = chain.neg_xy.at[row_n, slot_n].set(start_xy, mode="drop")
    neg_mask = chain.neg_mask.at[row_n, slot_n].set(True, mode="drop")
    neg_count = chain.neg_count + n_neg

    dirty = chain.dirty | (jnp.sum(onehot_k * learns[:, None], axis=0) > 0)
    return chain.replace(executions=executions, successes=successes, pos_xy=pos_xy,
                         pos_mask=pos_mask, pos_obs=pos_obs, pos_count=pos_count, neg_xy=neg_xy,
                         neg_mask=neg_mask, neg_count=neg_count, dirty=dirty, pess_ok=pess_ok,
                         robust_ok=robust_ok)


def ring_to_chronological(ring, head, count):
    """Unroll a per-env ring of positions into the oldest-first layout record_outcomes expects.

    ring: (T, 2) positions, head: int index of the next write, count: int positions written so far.
    Returns ((T, 2) oldest first, (T,) bool valid). vmap over envs.
    """
    T = ring.shape[0]
    idx = (jnp.asarray(head) + jnp.arange(T)) % T
    n = jnp.minimum(jnp.asarray(count), T)
    return ring[idx], jnp.arange(T) >= T - n


# ------------------------------------------------------------------------------------------------
# Refitting classifiers and the robust-sampling cache
# ------------------------------------------------------------------------------------------------

def refresh_subgoal_cache(chain: Chain, mask=None) -> Chain:
    """Recompute, for rows in ``mask`` (default: all fitted rows), which stored positive states
    lie in the row's own pessimistic region (``pess_ok``) and which also have their four
    neighbours xy +- subgoal_tolerance along each axis inside it (``robust_ok``)."""
    cfg = chain.cfg
    K, P, L = cfg.max_options, cfg.max_pos_traj, cfg.traj_len
    mask = chain.fitted if mask is None else jnp.asarray(mask, bool) & chain.fitted
    r = cfg.subgoal_tolerance
    shifts = jnp.array([[0.0, 0.0], [r, 0.0], [-r, 0.0], [0.0, r], [0.0, -r]], jnp.float32)
    pts = chain.pos_xy[:, :, :, None, :] + shifts                            # (K, P, L, 5, 2)
    pess = initiation.pessimistic_contains
    inside = jax.vmap(pess)(chain.clf, pts.reshape(K, P * L * 5, 2)).reshape(K, P, L, 5)
    inside = inside & chain.pos_mask[..., None] & chain.fitted[:, None, None, None]
    pess_ok = jnp.where(mask[:, None, None], inside[..., 0], chain.pess_ok)
    robust_ok = jnp.where(mask[:, None, None], inside.all(-1), chain.robust_ok)
    return chain.replace(pess_ok=pess_ok, robust_ok=robust_ok)


def refit(chain: Chain, mask=None, seed_axis=None) -> Chain:
    """Refit the initiation classifiers of the rows in ``mask`` (default: ``chain.dirty``), vmapped
    over all K rows (rows outside the mask see no data and keep their classifiers). Only rows in
    use, other than the global option, with at least one positive trajectory are fitted. Clears
    their dirty flags and refreshes their robust-sampling cache.

    ``seed_axis``: the name of an enclosing ``vmap`` axis over independent runs, if any; the fit
    then runs only when some run has a row to fit, not on every call."""
    cfg = chain.cfg
    K, P, L = cfg.max_options, cfg.max_pos_traj, cfg.traj_len
    mask = chain.dirty if mask is None else jnp.asarray(mask, bool)
    if mask.shape != (K,):
        raise ValueError(f"refit: mask must have shape ({K},), got {mask.shape}")
    has_pos = chain.pos_mask[:, :, 0].any(axis=1)
    do = mask & chain.active & (jnp.arange(K) != GLOBAL) & has_pos

    solver = svm.resolve_inner(None, backend=cfg.svm_backend)

    def fit(c):
        clf = initiation.fit_initiation_batch(
            c.pos_xy.reshape(K, P * L, 2), c.pos_mask.reshape(K, P * L), c.neg_xy, c.neg_mask,
            initiation_config(cfg), prev=c.clf, dirty=do, solver=solver)
        return refresh_subgoal_cache(c.replace(clf=clf, fitted=_fitted_flags(clf)), do)

    # nothing to fit (most iterations late in training): skip the set-up work entirely
    if seed_axis is None:
        chain = jax.lax.cond(do.any(), fit, lambda c: c, chain)
    else:
        def fit_some(c):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(do.any(), a, b), fit(c), c)
        any_do = jax.lax.psum(do.any().astype(jnp.int32), seed_axis) > 0
        chain = jax.lax.cond(any_do, fit_some, lambda c: c, chain)
    return chain.replace(dirty=chain.dirty & ~mask)


# ------------------------------------------------------------------------------------------------
# Growing the chain and chain-level metrics
# ------------------------------------------------------------------------------------------------

def start_covered(chain: Chain, start_xy) -> jax.Array:
    """bool: some mature option's initiation set (optimistic OR pessimistic) holds start_xy."""
    ini, _ = classify_all(chain, start_xy)
    return jnp.any(ini & (chain.status == MATURE))


def clear_row(chain: Chain, row, pred) -> Chain:
    """Where the scalar ``pred`` holds, forget everything row ``row`` learned: its counters,
    examples and classifiers (status and parent stay). For a link re-targeted in gestation, whose
    examples describe reaching another parent."""
    cfg = chain.cfg
    hit = (jnp.arange(cfg.max_options) == jnp.asarray(row)) & jnp.asarray(pred, bool)
    empty = _empty_classifiers(cfg)

    def keep(a, zero):
        m = hit.reshape((-1,) + (1,) * (a.ndim - 1))
        return jnp.where(m, zero, a)

    return chain.replace(
        successes=keep(chain.successes, 0), executions=keep(chain.executions, 0),
        pos_mask=keep(chain.pos_mask, False), pos_count=keep(chain.pos_count, 0),
        neg_mask=keep(chain.neg_mask, False), neg_count=keep(chain.neg_count, 0),
        clf=jax.tree_util.tree_map(keep, chain.clf, empty),
        fitted=keep(chain.fitted, False), dirty=keep(chain.dirty, False),
        pess_ok=keep(chain.pess_ok, False), robust_ok=keep(chain.robust_ok, False))


def mature_options(chain: Chain) -> Chain:
    """Options in gestation with at least ``gestation`` successes become mature (idempotent)."""
    matured = (chain.status == GESTATION) & (chain.successes >= chain.cfg.gestation)
    return chain.replace(status=jnp.where(matured, MATURE, chain.status))


def add_option(chain: Chain, parent, start_xy) -> Chain:
    """Algorithm 3, lines 7-9: if no option is in gestation, row ``parent`` (int32; -1: none) is
    mature with fitted classifiers (and, with ``ChainConfig.initiation_period`` > 0, has at least
    gestation + initiation_period successes), and no mature option's initiation set holds
    ``start_xy``, a new option is created in the next free row, in gestation, targeting
    ``parent``. When the table is full, ``capacity_hit`` is set instead (sticky)."""
    cfg = chain.cfg
    K = cfg.max_options
    status = chain.status
    parent_c = jnp.clip(parent, 0)
    want = ((~jnp.any(status == GESTATION)) & (parent >= 0) & chain.fitted[parent_c]
            & ~start_covered(chain, start_xy))
    if cfg.initiation_period > 0:   # DSC's initiation period (static: 0 adds nothing)
        want = want & (chain.successes[parent_c] >= cfg.gestation + cfg.initiation_period)
    n = chain.num_options
    room = n < K
    create = want & room
    slot = jnp.where(create, n, K)                      # K: out of bounds -> no write
    status = status.at[slot].set(GESTATION, mode="drop")
    parents = chain.parent.at[slot].set(parent, mode="drop")
    return chain.replace(status=status, parent=parents, num_options=n + create.astype(jnp.int32),
                         capacity_hit=chain.capacity_hit | (want & ~room))


def check_start(start_xy) -> jax.Array:
    """``start_xy`` as a float32 (2,) array; a ValueError for any other shape."""
    start_xy = jnp.asarray(start_xy, jnp.float32)
    if start_xy.shape != (2,):
        raise ValueError(f"grow_chain: start_xy must have shape (2,), got {start_xy.shape}")
    return start_xy


def grow_chain(chain: Chain, start_xy) -> Chain:
    """Maturity, then chain growth (call after :func:`refit`, once per learning iteration).

    1. Options in gestation with at least ``gestation`` successes become mature.
    2. If no option is in gestation, the newest mature option has fitted classifiers (and its
       initiation period is done: ``gestation + initiation_period`` successes, baseline DSC's
       rule), and no mature option's initiation set holds ``start_xy`` (pass the env's start
       state, ``env.start``), a new option is created in the next free row, in gestation, whose
       parent is the newest mature option (:func:`add_option`). When the table is full,
       ``capacity_hit`` is set instead (sticky).

    Beyond the paper, ``dscpp_jax.frontier.grow_chain`` picks the parent by the chain's frontier.
    """
    start_xy = check_start(start_xy)
    chain = mature_options(chain)
    newest = jnp.max(jnp.where(chain.status == MATURE, jnp.arange(chain.cfg.max_options), -1))
    return add_option(chain, newest, start_xy)


def success_rates(chain: Chain) -> jax.Array:
    """(K,) successes / executions per row (0 where never executed)."""
    ex = chain.executions
    return jnp.where(ex > 0, chain.successes / jnp.maximum(ex, 1), 0.0).astype(jnp.float32)


def chain_probability(chain: Chain) -> jax.Array:
    """Paper eq. 3: product over the chain (goal option and links in use, not the global option)
    of each option's successes / executions; an option never executed contributes 0."""
    in_chain = chain.active & (jnp.arange(chain.cfg.max_options) != GLOBAL)
    return jnp.prod(jnp.where(in_chain, success_rates(chain), 1.0))


# A point farther from any maze than an RBF kernel reaches (exp(-gamma * 2e12) is 0 in float32
# for any gamma above 1e-10): a region that holds it holds everything far from its examples.
UNBOUNDED_PROBE_XY = (1e6, 1e6)


def gestation_start_distances(chain: Chain):
    """Where the option in gestation has been tried from: the mean distance from the starts of
    its stored failed executions (the negatives, the last ``max_neg``) and of its successful
    ones (the positives' first states) to the nearest positive state of the option it targets
    (to the task goal when it is the goal option). Straight-line distances, walls ignored.
    Returns ``(failed, succeeded)``, float32 scalars, NaN where there is none (or nothing is in
    gestation)."""
    gest = chain.status == GESTATION
    g = jnp.argmax(gest)
    p = chain.parent[g]
    pc = jnp.clip(p, 0)
    K, P, L = chain.pos_mask.shape
    target = chain.pos_xy[pc].reshape(P * L, 2)
    tmask = chain.pos_mask[pc].reshape(P * L) & (p >= 0)
    # the goal option's target is the task goal (one point)
    target = jnp.concatenate([target, chain.goal_xy[None, :]], axis=0)
    tmask = jnp.concatenate([tmask, (p < 0)[None]], axis=0)

    def mean_nearest(xy, mask):
        d2 = jnp.sum((xy[:, None, :] - target[None, :, :]) ** 2, axis=-1)
        d = jnp.sqrt(jnp.min(jnp.where(tmask[None, :], d2, jnp.inf), axis=1))
        ok = mask & jnp.any(tmask) & jnp.any(gest)
        n = jnp.sum(ok)
        return jnp.where(n > 0, jnp.sum(jnp.where(ok, d, 0.0)) / jnp.maximum(n, 1), jnp.nan)

    failed = mean_nearest(chain.neg_xy[g], chain.neg_mask[g])
    succeeded = mean_nearest(chain.pos_xy[g, :, 0], chain.pos_mask[g, :, 0])
    return failed.astype(jnp.float32), succeeded.astype(jnp.float32)


TABLE_PREFIX = "table/"   # metric names of `table_columns` (the host writes them to options.csv)


def table_columns(chain: Chain) -> dict:
    """The option table row by row, (K,) int32 each: status, parent, executions and successes so
    far, positive trajectories and negative starts ever recorded (the history in a run's
    ``options.csv``; differences between two snapshots give a link's success over that span)."""
    return {"status": chain.status, "parent": chain.parent, "executions": chain.executions,
            "successes": chain.successes, "positives": chain.pos_count,
            "negatives": chain.neg_count}


def chain_metrics(chain: Chain, start_xy=None) -> dict:
    """Scalars for logging under ``options/...`` (reduced on the device)."""
    gest = chain.status == GESTATION
    fail_d, success_d = gestation_start_distances(chain)
    m = {
        "num_options": chain.num_options,
        "num_mature": jnp.sum(chain.status == MATURE),
        "num_gestation": jnp.sum(chain.status == GESTATION),
        "chain_probability": chain_probability(chain),
        "capacity_hit": chain.capacity_hit.astype(jnp.int32),
        "global_success_rate": success_rates(chain)[GLOBAL],
        "goal_success_rate": success_rates(chain)[GOAL],
        # the option in gestation (the chain's frontier; 0 while none): how often it has been
        # tried and has succeeded so far; it matures at `ChainConfig.gestation` successes
        "gestation_executions": jnp.sum(jnp.where(gest, chain.executions, 0)),
        "gestation_successes": jnp.sum(jnp.where(gest, chain.successes, 0)),
        # the row it targets (-1 while none)
        "gestation_parent": jnp.max(jnp.where(gest, chain.parent, -1)),
        # where it has been tried from: mean distance of its stored failed / successful starts
        # to its target's nearest positive state (NaN where none; `gestation_start_distances`)
        "gestation_fail_distance": fail_d,
        "gestation_success_distance": success_d,
        # mature options whose initiation set has no bound: the two-class SVC's value far from
        # every example is its intercept, and when an option's failures start among its
        # successes the fit can put that above zero, so the region holds the whole plane but
        # the examples' own neighbourhood (and counts the start as covered)
        "unbounded_regions": jnp.sum(classify_all(chain, UNBOUNDED_PROBE_XY)[0]
                                     & (chain.status == MATURE)),
    }
    if start_xy is not None:
        m["start_covered"] = start_covered(chain, start_xy).astype(jnp.int32)
    return m

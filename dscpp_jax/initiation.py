"""Initiation classifiers of an option: optimistic + pessimistic kernel SVMs (paper §3.1).

Dual variant (DSC++), refit from an option's positive examples (start states and the last states
of successful rollouts) and negative examples (start states of failed rollouts), x,y only:

* positives and negatives: optimistic = two-class RBF SVC (C = 1, class_weight "balanced" once
  there are ≥ 10 negatives); pessimistic = one-class ν-SVM (ν = 0.1) fit on the positives the SVC
  itself calls positive, as the paper's appendix describes (the previous pessimistic model is kept
  when there are none). The authors' code fit it on every training point the SVC calls positive,
  negatives included: ``InitiationConfig(pessimistic_examples="all")``;
* positives only: pessimistic = one-class ν = 0.1, optimistic = one-class ν = 0.01;
* no positives: nothing changes (an option never fitted contains nothing).

Initiation = optimistic OR pessimistic; other options target the pessimistic region.

Single variant (baseline DSC, Bagaria & Konidaris 2020; the authors' model-free baseline with
``--use_pessimistic_clf_only``): one model, the one-class ν-SVM (ν = ``nu_single``) fit

* with negatives: on every training point, positives and negatives together, that the two-class
  SVC (as above) calls positive (the previous model is kept when there are none), as the
  authors' ``train_two_class_classifier`` does;
* with positives only: on the positives.

That one model is both the initiation set and the region the next option targets (stored in both
fields, so optimistic = pessimistic).

Every switch above is a traced value on fixed, padded arrays + masks, so a fit is jit-able and
``fit_initiation_batch`` refits a batch of options at once with ``vmap`` (each problem's SMO loop
stops on its own).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from flax import struct

from dscpp_jax import svm
from dscpp_jax.svm import SVMModel

__all__ = [
    "InitiationConfig",
    "InitiationClassifiers",
    "empty_initiation",
    "fit_initiation",
    "fit_initiation_batch",
    "initiation_contains",
    "optimistic_contains",
    "pessimistic_contains",
]

VARIANTS = ("dual", "single")
# How fit_initiation_batch runs its options: "vmap" (one batched SMO loop that runs until the
# slowest option is done; best on accelerators, where a step costs the same for 1 or 16 options)
# or "map" (one option after another; on a CPU the work then scales with the options' own steps).
BATCH_MODE = {"cpu": "map", "default": "vmap"}


@dataclasses.dataclass(frozen=True)
class InitiationConfig:
    """Classifier hyperparameters (static, hashable).

    variant: "dual" (optimistic + pessimistic, DSC++) or "single" (baseline DSC).
    gamma: RBF width for x,y features (the original's "auto" = 1 / n_features = 0.5).
    C: SVC box constraint. nu_pessimistic / nu_optimistic: one-class ν of the pessimistic model
    and of the positives-only optimistic model. nu_single: ν of the single variant's one model
    (a one-class SVM). balanced_min_negatives: class_weight "balanced" from this many negatives on.
    tol, max_iter: SMO stopping tolerance and step cap (None: ``svm.default_max_iter``).
    pessimistic_examples: what the dual variant's pessimistic model is fit on: "positives" (the
    positives the SVC calls positive, the paper) or "all" (every training point the SVC calls
    positive, negatives included, as the authors' code did).
    """

    variant: str = "dual"
    gamma: float = 0.5
    C: float = 1.0
    nu_pessimistic: float = 0.1
    nu_optimistic: float = 0.01
    nu_single: float = 0.1
    balanced_min_negatives: int = 10
    tol: float = 1e-3
    max_iter: int | None = None
    pessimistic_examples: str = "positives"

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if not self.gamma > 0:
            raise ValueError(f"gamma must be > 0, got {self.gamma}")
        if not self.C > 0:
            raise ValueError(f"C must be > 0, got {self.C}")
        for name in ("nu_pessimistic", "nu_optimistic", "nu_single"):
            v = getattr(self, name)
            if not 0 < v <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {v}")
        if not self.tol > 0:
            raise ValueError(f"tol must be > 0, got {self.tol}")
        if self.max_iter is not None and (not isinstance(self.max_iter, int) or self.max_iter < 1):
            raise ValueError(f"max_iter must be a positive int or None, got {self.max_iter!r}")
        if self.pessimistic_examples not in ("positives", "all"):
            raise ValueError(f"pessimistic_examples must be 'positives' or 'all', got {self.pessimistic_examples!r}")
        if self.balanced_min_negatives < 0:
            raise ValueError("balanced_min_negatives must be >= 0")


@struct.dataclass
class InitiationClassifiers:
    """One option's classifiers over ``num_pos + num_neg`` padded training slots.

    optimistic / pessimistic: SVMModel (identical in the single variant: its one model).
    optimistic_fitted / pessimistic_fitted: () bool; an unfitted model contains nothing.
    """

    optimistic: SVMModel
    pessimistic: SVMModel
    optimistic_fitted: jax.Array
    pessimistic_fitted: jax.Array


def _empty_model(n: int, dim: int, gamma: float) -> SVMModel:
    return SVMModel(
        support=jnp.zeros((n, dim), jnp.float32),
        coef=jnp.zeros((n,), jnp.float32),
        rho=jnp.ones((), jnp.float32),
        gamma=jnp.asarray(gamma, jnp.float32),
        mask=jnp.zeros((n,), bool),
        one_class=jnp.zeros((), bool),
        converged=jnp.ones((), bool),
        n_iter=jnp.zeros((), jnp.int32),
        gap=jnp.zeros((), jnp.float32),
    )


def empty_initiation(num_pos: int, num_neg: int, dim: int = 2, gamma: float = 0.5) -> InitiationClassifiers:
    """Unfitted classifiers with the shapes ``fit_initiation`` returns for these slot counts."""
    if num_pos < 1 or num_neg < 0:
        raise ValueError(f"need num_pos >= 1 and num_neg >= 0, got {num_pos}, {num_neg}")
    m = _empty_model(num_pos + num_neg, dim, gamma)
    f = jnp.zeros((), bool)
    return InitiationClassifiers(optimistic=m, pessimistic=m, optimistic_fitted=f, pessimistic_fitted=f)


def _select(flag, a, b):
    """Pytree-wise where(flag, a, b) for a scalar (traced) flag."""
    return jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)


def _check_inputs(pos_xy, pos_mask, neg_xy, neg_mask):
    if getattr(pos_xy, "ndim", None) != 2 or getattr(neg_xy, "ndim", None) != 2:
        raise ValueError(
            f"pos_xy and neg_xy must be (n, d) arrays, got {getattr(pos_xy, 'shape', None)} and "
            f"{getattr(neg_xy, 'shape', None)} (use fit_initiation_batch for a batch of options)"
        )
    if pos_xy.shape[1] != neg_xy.shape[1]:
        raise ValueError(f"pos_xy and neg_xy need the same feature size, got {pos_xy.shape} and {neg_xy.shape}")
    if pos_xy.shape[0] < 1:
        raise ValueError("pos_xy needs at least one slot")
    if getattr(pos_mask, "shape", None) != pos_xy.shape[:1]:
        raise ValueError(f"pos_mask must have shape {pos_xy.shape[:1]}, got {getattr(pos_mask, 'shape', None)}")
    if getattr(neg_mask, "shape", None) != neg_xy.shape[:1]:
        raise ValueError(f"neg_mask must have shape {neg_xy.shape[:1]}, got {getattr(neg_mask, 'shape', None)}")


@functools.partial(jax.jit, static_argnames=("cfg", "inner"))
def _fit(pos_xy, pos_mask, neg_xy, neg_mask, prev: InitiationClassifiers, cfg: InitiationConfig,
         inner) -> InitiationClassifiers:
    pos_mask = pos_mask.astype(bool)
    neg_mask = neg_mask.astype(bool)
    X = svm.clean_points(jnp.concatenate([pos_xy, neg_xy], axis=0), jnp.concatenate([pos_mask, neg_mask]))
    labels = jnp.concatenate([jnp.ones_like(pos_mask, jnp.int32), jnp.zeros_like(neg_mask, jnp.int32)])
    pos_slots = jnp.concatenate([pos_mask, jnp.zeros_like(neg_mask)])
    all_slots = jnp.concatenate([pos_mask, neg_mask])
    has_pos = jnp.any(pos_mask)
    has_neg = jnp.any(neg_mask)
    two_class = has_pos & has_neg
    balanced = jnp.sum(neg_mask) >= cfg.balanced_min_negatives
    max_iter = svm.check_max_iter(cfg.max_iter, X.shape[0])
    gamma = jnp.float32(cfg.gamma)
    tol = jnp.float32(cfg.tol)

    # first model: SVC with negatives, else one-class on the positives (one SMO run either way;
    # the single variant's is only the SVC that picks the one-class model's points)
    nu_first = cfg.nu_optimistic if cfg.variant == "dual" else cfg.nu_single
    svc = svm.svc_problem(labels, all_slots, jnp.float32(cfg.C), balanced)
    n = X.shape[0]
    occ = svm.one_class_problem(X, pos_slots, jnp.float32(nu_first), gamma,
                                 svm.one_class_start_bound(nu_first, n))
    problem = tuple(jnp.where(two_class, a, b) for a, b in zip(svc, occ))
    first_mask = jnp.where(two_class, all_slots, pos_slots)
    first, f_train = svm.fit_problem(X, first_mask, problem, ~two_class, gamma, tol, max_iter, inner)
    opt = _select(has_pos, first, prev.optimistic)
    opt_fitted = has_pos | prev.optimistic_fitted

    # pessimistic (the single variant's one model): one-class ν on the training points the SVC
    # calls positive (the dual variant: its positives only, unless pessimistic_examples="all";
    # the single variant: positives and negatives, as the authors' code); all positives when
    # there was no SVC
    single = cfg.variant == "single"
    called_pos = f_train >= 0  # the SVC's own training predictions (two-class rule: f >= 0)
    candidates = all_slots if single or cfg.pessimistic_examples == "all" else pos_slots
    pes_slots = jnp.where(two_class, candidates & called_pos, pos_slots)
    any_pes = jnp.any(pes_slots)
    nu_pes = cfg.nu_single if single else cfg.nu_pessimistic
    pes_problem = svm.one_class_problem(X, pes_slots, jnp.float32(nu_pes), gamma,
                                         svm.one_class_start_bound(nu_pes, n))
    pes_new, _ = svm.fit_problem(X, pes_slots, pes_problem, True, gamma, tol, max_iter, inner)
    pes = _select(any_pes, pes_new, prev.pessimistic)
    pes_fitted = any_pes | prev.pessimistic_fitted
    if single:
        return InitiationClassifiers(optimistic=pes, pessimistic=pes, optimistic_fitted=pes_fitted,
                                     pessimistic_fitted=pes_fitted)
    return InitiationClassifiers(optimistic=opt, pessimistic=pes, optimistic_fitted=opt_fitted,
                                 pessimistic_fitted=pes_fitted)


def fit_initiation(pos_xy, pos_mask, neg_xy, neg_mask, cfg: InitiationConfig = InitiationConfig(),
                   prev: InitiationClassifiers | None = None, *, solver=None
                   ) -> InitiationClassifiers:
    """Refit one option's classifiers.

    pos_xy (P, d), pos_mask (P,), neg_xy (M, d), neg_mask (M,): padded examples + validity.
    prev: the option's current classifiers (kept where a model cannot be refit: no positives, or
    no positive the SVC calls positive); None = unfitted. Jit-able; no retrace across counts.
    solver: the SMO solver (``svm.resolve_inner``'s argument; None: the platform's default).
    """
    _check_inputs(pos_xy, pos_mask, neg_xy, neg_mask)
    if prev is None:
        prev = empty_initiation(pos_xy.shape[0], neg_xy.shape[0], pos_xy.shape[1], cfg.gamma)
    return _fit(pos_xy, pos_mask, neg_xy, neg_mask, prev, cfg=cfg, inner=svm.resolve_inner(solver))


def fit_initiation_batch(pos_xy, pos_mask, neg_xy, neg_mask, cfg: InitiationConfig = InitiationConfig(),
                         prev: InitiationClassifiers | None = None, dirty=None, *,
                         solver=None) -> InitiationClassifiers:
    """Refit a batch of K options at once (vmapped SMO on accelerators, see ``BATCH_MODE``).

    pos_xy (K, P, d), pos_mask (K, P), neg_xy (K, M, d), neg_mask (K, M); prev: batched
    classifiers (leading K) or None; dirty: (K,) bool, options to refit (others keep ``prev``
    and cost no SMO steps); solver: as in ``fit_initiation``. Returns batched
    InitiationClassifiers.
    """
    if getattr(pos_xy, "ndim", None) != 3 or getattr(neg_xy, "ndim", None) != 3:
        raise ValueError(f"batched pos_xy / neg_xy must be (K, n, d), got {getattr(pos_xy, 'shape', None)} "
                         f"and {getattr(neg_xy, 'shape', None)}")
    K = pos_xy.shape[0]
    if neg_xy.shape[0] != K:
        raise ValueError(f"pos_xy and neg_xy need the same number of options, got {K} and {neg_xy.shape[0]}")
    _check_inputs(pos_xy[0], pos_mask[0] if getattr(pos_mask, "ndim", 0) == 2 else pos_mask,
                  neg_xy[0], neg_mask[0] if getattr(neg_mask, "ndim", 0) == 2 else neg_mask)
    if pos_mask.shape != pos_xy.shape[:2] or neg_mask.shape != neg_xy.shape[:2]:
        raise ValueError(f"masks must have shapes {pos_xy.shape[:2]} and {neg_xy.shape[:2]}, "
                         f"got {pos_mask.shape} and {neg_mask.shape}")
    if prev is None:
        one = empty_initiation(pos_xy.shape[1], neg_xy.shape[1], pos_xy.shape[2], cfg.gamma)
        prev = jax.tree.map(lambda x: jnp.broadcast_to(x, (K,) + x.shape), one)
    if dirty is None:
        dirty = jnp.ones((K,), bool)
    else:
        dirty = jnp.asarray(dirty, bool)
        if dirty.shape != (K,):
            raise ValueError(f"dirty must have shape ({K},), got {dirty.shape}")

    mode = BATCH_MODE.get(jax.default_backend(), BATCH_MODE["default"])
    return _fit_batch(pos_xy, pos_mask, neg_xy, neg_mask, prev, dirty, cfg=cfg,
                      inner=svm.resolve_inner(solver), mode=mode)


@functools.partial(jax.jit, static_argnames=("cfg", "inner", "mode"))
def _fit_batch(pos_xy, pos_mask, neg_xy, neg_mask, prev, dirty, cfg, inner, mode="vmap"):
    def one(args):
        p, pm, n, nm, pr, d = args
        new = _fit(p, pm & d, n, nm & d, pr, cfg=cfg, inner=inner)  # clean options: 0 SMO steps
        return _select(d, new, pr)

    args = (pos_xy, pos_mask.astype(bool), neg_xy, neg_mask.astype(bool), prev, dirty)
    if mode == "map":
        return jax.lax.map(one, args)
    return jax.vmap(lambda *a: one(a))(*args)


def optimistic_contains(clf: InitiationClassifiers, xy) -> jax.Array:
    """xy (..., d) inside the optimistic model (False when unfitted)."""
    return clf.optimistic_fitted & svm.predict(clf.optimistic, xy)


def pessimistic_contains(clf: InitiationClassifiers, xy) -> jax.Array:
    """xy (..., d) inside the pessimistic model, the region other options target."""
    return clf.pessimistic_fitted & svm.predict(clf.pessimistic, xy)


def initiation_contains(clf: InitiationClassifiers, xy) -> jax.Array:
    """Initiation test: optimistic OR pessimistic (the single variant's one classifier)."""
    return optimistic_contains(clf, xy) | pessimistic_contains(clf, xy)

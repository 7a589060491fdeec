"""RBF kernel SVMs fitted on the accelerator with libsvm's SMO solver.

Two problems, both in libsvm's dual form ``min ½ αᵀQα + pᵀα  s.t. 0 ≤ α_i ≤ C_i, yᵀα = Δ``:

* C-SVC (``fit_svc``): ``Q_ij = y_i y_j K_ij``, ``p = -1``, ``α₀ = 0``; labels 1 → y = +1,
  labels 0 → y = -1; ``C_i = C · w_class(i)``.
* one-class ν-SVM (``fit_one_class``): ``Q = K``, ``p = 0``, ``C_i = 1``, ``Σα = ν·l``, started
  from libsvm's feasible point (the first ⌊ν·l⌋ valid points at 1, the next at the remainder).

The solver is SMO with second-order working-set selection (Fan, Chen & Lin 2005), the algorithm
libsvm (and so scikit-learn's ``SVC`` / ``OneClassSVM``) uses. Each step needs two kernel rows,
computed on the fly from the points, so no n×n matrix is ever stored. It runs in a
``lax.while_loop`` with an iteration cap and a per-problem ``done`` flag, so a ``vmap``-ped batch of
problems with different sizes finishes each problem independently (finished problems stop
changing). On GPUs (``backend="auto"``) the whole loop of one problem runs instead inside one
Pallas (Triton) kernel program, one program per problem of a vmapped batch, over the problem's
valid points compacted to the front: the same steps, without a kernel launch and host sync per
step (``_solve_pallas``). Inputs are padded to a fixed number of slots and masked: padded slots
get ``C_i = 0`` and never enter the working set, so the padding size never changes the solution
(whatever padded rows hold is replaced by zeros, NaN included).

Decision convention (``decision_function``): ``f(x) = Σ_i coef_i K(x_i, x) − ρ`` with
``coef_i = y_i α_i``, positive means inside. Ties follow scikit-learn: a two-class model calls
``f ≥ 0`` positive, a one-class model calls ``f > 0`` inside (``predict`` applies the right one).

Everything is float32, jit-able and vmap-able. scikit-learn is only a test oracle: on DSC-like data
the decisions agree with ``SVC`` / ``OneClassSVM`` on ≥ 99.99 % of a dense grid (all of it away
from the boundary), see ``tests/test_svm.py`` and ``experiments/results/bench_options.md``.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

__all__ = [
    "SVMModel",
    "fit_svc",
    "fit_one_class",
    "decision_function",
    "predict",
    "default_max_iter",
    "one_class_start_bound",
    "resolve_inner",
    "svc_problem",
    "one_class_problem",
    "fit_problem",
    "clean_points",
    "check_max_iter",
]

# libsvm's floor on the curvature a_ij of a working pair.
_TAU = 1e-12
# SMO steps between two convergence checks of the while loop, per backend. On a GPU each check of
# a data-dependent while loop costs a device-to-host sync, so several (masked) steps per check are
# cheaper; on a CPU one step per check compiles faster and runs faster. Results do not depend on
# it (a finished problem's extra steps are no-ops).
INNER_STEPS = {"cpu": 1, "default": 8}
# argmax as one variadic (value, index) reduction, or as max + min-index (two plain reductions,
# much faster on XLA:CPU).
VARIADIC_ARGMAX = {"cpu": False, "default": True}
# Where the SMO loop runs with backend="auto": "pallas" = the whole loop of one problem inside one
# GPU kernel (Pallas, Triton backend), "xla" = a lax.while_loop of XLA ops (any platform).
AUTO_BACKEND = {"gpu": "pallas", "default": "xla"}
BACKENDS = ("auto", "xla", "pallas")
# Pallas kernel: points per chunk of the per-step sweeps (a power of two), warps per problem, and
# the largest problem kept in registers. Measured on an H200 (16 DSC-like options, 1,000 / 2,000 /
# 5,000 points each): 2048 / 8 / 1024 is within 0.2 ms of the fastest setting tried at 1,000
# points and within 0.9 ms at 2,000 and 5,000 (experiments/results/bench_options.md).
PALLAS_CHUNK = 2048
PALLAS_WARPS = 8
PALLAS_RESIDENT = 1024


class Solver(NamedTuple):
    """Static SMO solver setting (hashable: part of the jit cache key).

    backend:   "xla" (``lax.while_loop`` of XLA ops) or "pallas" (one fused kernel per problem).
    steps:     SMO steps between two convergence checks of the while loop (xla, and pallas in
               registers).
    variadic:  argmax as one variadic reduction (else max, then the min index at the max).
    chunk:     pallas: points per chunk of the kernel's sweeps (a power of two).
    warps:     pallas: warps of the program that solves one problem.
    resident:  pallas: a problem of at most this many points (a power of two; 0 = none) keeps α, G
               and its points in registers (larger ones sweep them in global memory every step).
    interpret: pallas: run the kernel in Pallas interpret mode (any platform; slow, for tests).
    """

    steps: int = 1
    variadic: bool = False
    backend: str = "xla"
    chunk: int = PALLAS_CHUNK
    warps: int = PALLAS_WARPS
    resident: int = PALLAS_RESIDENT
    interpret: bool = False


def _check_backend(backend):
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def resolve_inner(inner=None, backend="auto") -> Solver:
    """The static ``Solver`` for this platform (part of a fit's jit cache key).

    ``inner``: None (platform defaults), a ``Solver`` (used as given, checked), an int (XLA steps
    per convergence check) or a ``(steps, variadic)`` tuple (XLA loop settings; both select the
    XLA solver). ``backend``: "auto" (``AUTO_BACKEND``), "xla" or "pallas"; "pallas" off a GPU
    runs the kernel in interpret mode.
    """
    _check_backend(backend)
    platform = jax.default_backend()
    if isinstance(inner, Solver):
        sv = inner
    else:
        variadic = VARIADIC_ARGMAX.get(platform, VARIADIC_ARGMAX["default"])
        steps = INNER_STEPS.get(platform, INNER_STEPS["default"])
        if backend == "auto":
            backend = "xla" if inner is not None else AUTO_BACKEND.get(platform, AUTO_BACKEND["default"])
        if isinstance(inner, tuple):
            if len(inner) != 2:
                raise ValueError(f"inner must be (steps, variadic), got {inner!r}")
            steps, variadic = inner
        elif inner is not None:
            steps = inner
        sv = Solver(steps=steps, variadic=bool(variadic), backend=backend)
    if not isinstance(sv.steps, (int, np.integer)) or isinstance(sv.steps, bool) or sv.steps < 1:
        raise ValueError(f"inner steps must be a positive int, got {sv.steps!r}")
    if sv.backend not in ("xla", "pallas"):
        raise ValueError(f"a resolved solver backend must be 'xla' or 'pallas', got {sv.backend!r}")
    c = sv.chunk
    if not isinstance(c, (int, np.integer)) or c < 16 or c & (c - 1):
        raise ValueError(f"chunk must be a power of two >= 16, got {c!r}")
    r = sv.resident
    if not isinstance(r, (int, np.integer)) or isinstance(r, bool) or (r != 0 and (r < 16 or r & (r - 1))):
        raise ValueError(f"resident must be 0 or a power of two >= 16, got {r!r}")
    if not isinstance(sv.warps, (int, np.integer)) or sv.warps < 1 or sv.warps & (sv.warps - 1):
        raise ValueError(f"warps must be a power of two, got {sv.warps!r}")
    # off a GPU the kernel can only run interpreted
    interpret = sv.backend == "pallas" and (bool(sv.interpret) or platform != "gpu")
    return sv._replace(steps=int(sv.steps), variadic=bool(sv.variadic), chunk=int(c),
                       warps=int(sv.warps), resident=int(sv.resident), interpret=interpret)


# Query rows per block in kernel sums (bounds memory at block × n_train floats).
_BLOCK = 512


@struct.dataclass
class SVMModel:
    """A fitted RBF SVM over fixed, padded training slots.

    support:   (n, d) training points (every slot; non-support slots have ``coef == 0``).
    coef:      (n,) ``y_i α_i`` (0 on padding and non-support vectors).
    rho:       () intercept; ``f(x) = Σ coef_i K(support_i, x) − rho``.
    gamma:     () RBF width, ``K(a, b) = exp(−gamma ‖a − b‖²)``.
    mask:      (n,) bool, the valid training slots.
    one_class: () bool, True for a one-class model (inside iff f > 0), False for C-SVC (f ≥ 0).
    converged: () bool, the SMO gap fell below ``tol`` before the iteration cap.
    n_iter:    () int32, SMO steps taken.
    gap:       () float32, final maximal KKT violation (``Gmax + Gmax2`` in libsvm).
    """

    support: jax.Array
    coef: jax.Array
    rho: jax.Array
    gamma: jax.Array
    mask: jax.Array
    one_class: jax.Array
    converged: jax.Array
    n_iter: jax.Array
    gap: jax.Array


# --------------------------------------------------------------------------------------------
# Argument checks (trace time; only concrete values can be checked)




def _concrete(value: Any):
    """The value as a NumPy array, or None when it is traced."""
    try:
        return np.asarray(value)
    except Exception:  # a tracer: cannot be checked at trace time
        return None


def _check_range(name: str, value: Any, lo: float, hi: float | None, lo_open: bool = True):
    v = _concrete(value)
    if v is None:
        return
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    bad_lo = np.any(v <= lo) if lo_open else np.any(v < lo)
    bad_hi = hi is not None and np.any(v > hi)
    if bad_lo or bad_hi:
        interval = f"({lo}, {hi}]" if hi is not None else f"> {lo}"
        raise ValueError(f"{name} must be in {interval}, got {value!r}")


def _check_points(X, mask, labels=None):
    if getattr(X, "ndim", None) != 2:
        raise ValueError(f"X must be a (n, d) array of points, got shape {getattr(X, 'shape', None)}")
    n = X.shape[0]
    if n == 0:
        raise ValueError("X needs at least one slot (pad with masked-out rows instead)")
    if getattr(mask, "shape", None) != (n,):
        raise ValueError(f"mask must have shape ({n},) to match X {X.shape}, got {getattr(mask, 'shape', None)}")
    if labels is not None and getattr(labels, "shape", None) != (n,):
        raise ValueError(f"labels must have shape ({n},) to match X {X.shape}, got {getattr(labels, 'shape', None)}")


def default_max_iter(n_slots: int) -> int:
    """Iteration cap used when ``max_iter`` is None: ``max(10_000, 4 · n_slots)``."""
    return max(10_000, 4 * int(n_slots))


def check_max_iter(max_iter, n):
    """``max_iter`` as a positive int (``default_max_iter(n)`` for None); a ValueError otherwise."""
    if max_iter is None:
        return default_max_iter(n)
    if not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive int or None, got {max_iter!r}")
    return int(max_iter)


# --------------------------------------------------------------------------------------------
# Kernels


def _kernel_row(Xt, i, gamma):
    """K(X_t, X_i) for all t: (n,), from feature-major points Xt (d, n)."""
    d2 = (Xt[0] - Xt[0, i]) ** 2
    for k in range(1, Xt.shape[0]):
        d2 = d2 + (Xt[k] - Xt[k, i]) ** 2
    return jnp.exp(-gamma * d2)


def _kernel_block(Xt, coef, Qt, gamma):
    """Σ_i coef_i K(X_i, q) for the queries Qt (d, b): (b,).

    Feature by feature (no 3-D intermediate) and an elementwise product + sum rather than a
    matmul, which keeps full float32 precision on GPUs whose matmuls default to TF32.
    """
    d2 = (Qt[0][:, None] - Xt[0][None, :]) ** 2
    for k in range(1, Xt.shape[0]):
        d2 = d2 + (Qt[k][:, None] - Xt[k][None, :]) ** 2
    return jnp.sum(jnp.exp(-gamma * d2) * coef[None, :], axis=1)


def _kernel_sum(X, coef, Xq, gamma):
    """Σ_i coef_i K(X_i, Xq_q) for every query row, ``_BLOCK`` queries at a time: (q,)."""
    Xt, Qt = X.T, Xq.T
    q = Xq.shape[0]
    if q <= _BLOCK:
        return _kernel_block(Xt, coef, Qt, gamma)
    nb = -(-q // _BLOCK)
    Qt = jnp.pad(Qt, ((0, 0), (0, nb * _BLOCK - q)))

    def body(b, out):
        qb = jax.lax.dynamic_slice_in_dim(Qt, b * _BLOCK, _BLOCK, axis=1)
        return jax.lax.dynamic_update_slice_in_dim(out, _kernel_block(Xt, coef, qb, gamma), b * _BLOCK, 0)

    out = jax.lax.fori_loop(0, nb, body, jnp.zeros((nb * _BLOCK,), jnp.result_type(coef, jnp.float32)))
    return out[:q]


# --------------------------------------------------------------------------------------------
# SMO


@struct.dataclass
class _SMOState:
    alpha: jax.Array
    G: jax.Array
    it: jax.Array
    done: jax.Array


def _argmax(v, variadic):
    """(first index of the maximum, maximum)."""
    if variadic:
        i = jnp.argmax(v)
        return i, v[i]
    m = jnp.max(v)
    idx = jnp.min(jnp.where(v == m, jnp.arange(v.shape[0], dtype=jnp.int32), v.shape[0] - 1))
    return idx, m


def _working_set(y, Cv, alpha, G, variadic=False):
    """libsvm's index sets and maximal violations: (I_up, I_low, i, Gmax, gap)."""
    up = jnp.where(y > 0, alpha < Cv, alpha > 0)
    low = jnp.where(y > 0, alpha > 0, alpha < Cv)
    score_up = jnp.where(up, -y * G, -jnp.inf)
    i, gmax = _argmax(score_up, variadic)
    gmax2 = jnp.max(jnp.where(low, y * G, -jnp.inf))
    return up, low, i, gmax, gmax + gmax2


def _smo_step(Xt, y, Cv, gamma, tol, max_iter, variadic, s: _SMOState) -> _SMOState:
    alpha, G = s.alpha, s.G
    _, low, i, gmax, gap = _working_set(y, Cv, alpha, G, variadic)
    Ki = _kernel_row(Xt, i, gamma)
    b = gmax + y * G
    a = 2.0 - 2.0 * Ki  # K_ii + K_jj − 2 K_ij with K_tt = 1 for the RBF kernel
    a = jnp.where(a > 0, a, _TAU)
    obj = jnp.where(low & (b > 0), -(b * b) / a, jnp.inf)
    j, obj_min = _argmax(-obj, variadic)
    found = jnp.isfinite(obj_min)
    stop = (gap < tol) | (~found) | (~jnp.isfinite(gap))
    active = (~s.done) & (~stop) & (s.it < max_iter)

    Kj = _kernel_row(Xt, j, gamma)
    yi, yj = y[i], y[j]
    room_i = jnp.where(yi > 0, Cv[i] - alpha[i], alpha[i])
    room_j = jnp.where(yj > 0, alpha[j], Cv[j] - alpha[j])
    t_free = b[j] / a[j]
    t = jnp.minimum(t_free, jnp.minimum(room_i, room_j))
    t = jnp.where(active, jnp.maximum(t, 0.0), 0.0)
    # land exactly on a bound when the step is clipped there (float32 round-off otherwise leaves
    # a sliver of room that would keep the index in the working set)
    bound_i = jnp.where(yi > 0, Cv[i], 0.0)
    bound_j = jnp.where(yj > 0, 0.0, Cv[j])
    new_ai = jnp.where(active & (t >= room_i), bound_i, alpha[i] + yi * t)
    new_aj = jnp.where(active & (t >= room_j), bound_j, alpha[j] - yj * t)
    alpha = alpha.at[i].set(new_ai).at[j].set(new_aj)
    G = G + (y * t) * (Ki - Kj)  # G_k += Q_ik Δα_i + Q_jk Δα_j
    return _SMOState(
        alpha=alpha,
        G=G,
        it=s.it + active.astype(jnp.int32),
        done=s.done | (stop & (s.it < max_iter)),
    )


def _solve(X, y, Cv, alpha0, G0, gamma, tol, max_iter: int, inner: Solver):
    """Run SMO from a feasible (alpha0, G0 = Qα₀ + p). Returns (alpha, G, n_iter, gap).

    inner: the static ``Solver`` (see ``resolve_inner``).
    """
    if inner.backend == "pallas":
        return _solve_pallas(X, y, Cv, alpha0, G0, gamma, tol, max_iter, inner)
    steps, variadic = inner.steps, inner.variadic
    step = functools.partial(_smo_step, X.T, y, Cv, gamma, tol, max_iter, variadic)

    def body(s):
        if steps == 1:
            return step(s)
        return jax.lax.fori_loop(0, steps, lambda _, c: step(c), s, unroll=True)

    def cond(s):
        return (~s.done) & (s.it < max_iter)

    s0 = _SMOState(alpha=alpha0, G=G0, it=jnp.zeros((), jnp.int32), done=jnp.zeros((), bool))
    s = jax.lax.while_loop(cond, body, s0)
    _, _, _, _, gap = _working_set(y, Cv, s.alpha, s.G)
    gap = jnp.where(jnp.isfinite(gap), gap, 0.0)  # an empty working set is optimal
    return s.alpha, s.G, s.it, gap


# --------------------------------------------------------------------------------------------
# SMO in one Pallas kernel per problem
#
# The XLA loop above costs a few kernel launches and a device-to-host sync per step whatever the
# size, which dominates on a GPU at DSC's sizes. Here the whole loop of one problem runs inside one
# program of a Pallas (Triton) kernel; a vmapped call puts one program per problem on the grid.
#
# The problem's slots (C_i > 0 or α_i ≠ 0) are first compacted, in slot order, to the front, so a
# step's work scales with the valid points, not with the padded size. Kernel rows are recomputed
# from the points (no Gram matrix). Two paths, chosen per problem inside the kernel:
# * at most ``resident`` points: α, G and the points stay in registers; one step is one pass
#   (K_i row, second-order j, update, next i);
# * larger problems: α and G live in the kernel's outputs in global memory (L1/L2 resident at these
#   sizes) and one step is two sweeps over ⌈n_valid / chunk⌉ chunks:
#     B: K_i row, b and a, and the second-order choice of j (given i and Gmax from sweep A);
#     A: α_i, α_j and G update, then the next step's i, Gmax and max_{I_low} y G (the gap).
# Ties keep the first index and the per-element arithmetic is the XLA loop's, so both backends
# follow the same path up to float rounding (bit for bit in interpret mode on XLA:CPU; GPUs round
# exp differently, which can reorder near-ties late in a run).


def _smo_kernel(d: int, chunk: int, n_chunks: int, max_iter: int, variadic: bool, resident: int,
                steps: int, barrier: bool):

    CH = chunk
    f32 = jnp.float32
    NEG = -jnp.inf

    def finite(v):  # isfinite for scalars, NaN → False
        return (v > -jnp.inf) & (v < jnp.inf)

    def sync():  # make this program's global-memory writes visible to all its threads
        if barrier:
            plgpu.debug_barrier()

    def kernel(xt_ref, y_ref, c_ref, a0_ref, g0_ref, n_ref, par_ref, al_ref, g_ref, it_ref, gap_ref):
        n_act = n_ref[0]
        gamma = par_ref[0]
        tol = par_ref[1]
        nch = (n_act + (CH - 1)) // CH
        lane = jax.lax.broadcasted_iota(jnp.int32, (CH,), 0)

        def sl(c):
            start = c * CH if isinstance(c, int) else pl.multiple_of(c * CH, CH)
            return pl.ds(start, CH)

        def krow(xrows, xs):  # K(X_t, x) over a chunk, as _kernel_row computes it
            d2 = (xrows[0] - xs[0]) ** 2
            for k in range(1, d):
                d2 = d2 + (xrows[k] - xs[k]) ** 2
            return jnp.exp(-gamma * d2)

        def xrows_at(s):
            return [xt_ref[k, s] for k in range(d)]

        def point(i):  # the point of slot i (X is read-only: plain loads are safe)
            return tuple(xt_ref[k, i] for k in range(d))

        def first_max(v, base, carry):
            """Fold (max of v, slot of its first occurrence) into a running (max, slot); v holds
            the slots base, base + 1, ..."""
            best, idx = carry
            m = jnp.max(v)
            if variadic:  # an independent (value, index) reduction: both run side by side
                k = jnp.argmax(v).astype(jnp.int32)
            else:
                k = jnp.min(jnp.where(v == m, jax.lax.broadcasted_iota(jnp.int32, v.shape, 0), v.shape[0]))
            better = m > best
            return jnp.where(better, m, best), jnp.where(better, base + k, idx)

        def select(base, al, G, yv, cv, carry):
            """I_up argmax of −yG (i, Gmax) and the I_low max of yG over one chunk."""
            best, i, m2 = carry
            up = jnp.where(yv > 0, al < cv, al > 0)
            low = jnp.where(yv > 0, al > 0, al < cv)
            best, i = first_max(jnp.where(up, -yv * G, NEG), base, (best, i))
            m2 = jnp.maximum(m2, jnp.max(jnp.where(low, yv * G, NEG)))
            return best, i, m2

        def second_order(base, al, G, yv, cv, Ki, gmax, carry):
            """Fold a chunk's j = argmin over I_low, b_j > 0, of −b_j² / a_ij (as max of b²/a)."""
            low = jnp.where(yv > 0, al > 0, al < cv)
            b = gmax + yv * G
            a = 2.0 - 2.0 * Ki
            a = jnp.where(a > 0, a, _TAU)
            return first_max(jnp.where(low & (b > 0), (b * b) / a, NEG), base, carry)

        def pair_step(found, gmax, xi, xj, ai, yi, ci, aj, gj, yj, cj):
            """The clipped two-variable step: (t, new α_i, new α_j), as _smo_step computes it."""
            d2 = (xj[0] - xi[0]) ** 2
            for k in range(1, d):
                d2 = d2 + (xj[k] - xi[k]) ** 2
            a_ij = 2.0 - 2.0 * jnp.exp(-gamma * d2)
            a_ij = jnp.where(a_ij > 0, a_ij, _TAU)
            b_j = gmax + yj * gj
            room_i = jnp.where(yi > 0, ci - ai, ai)
            room_j = jnp.where(yj > 0, aj, cj - aj)
            t = jnp.minimum(b_j / a_ij, jnp.minimum(room_i, room_j))
            t = jnp.where(found, jnp.maximum(t, 0.0), 0.0)
            new_ai = jnp.where(found & (t >= room_i), jnp.where(yi > 0, ci, 0.0), ai + yi * t)
            new_aj = jnp.where(found & (t >= room_j), jnp.where(yj > 0, 0.0, cj), aj - yj * t)
            return t, new_ai, new_aj

        sel0 = (f32(NEG), jnp.int32(0), f32(NEG))

        def converged(gap):  # gap below tol, or an empty working set (gap = -inf)
            return (gap < tol) | (~finite(gap))

        def cond(carry):
            it, done = carry[:2]
            return (~done) & (it < max_iter)

        def copy(c, _):
            al_ref[sl(c)] = a0_ref[sl(c)]
            g_ref[sl(c)] = g0_ref[sl(c)]
            return 0

        jax.lax.fori_loop(0, n_chunks, copy, 0)

        def chunked():
            """α and G in global memory, two sweeps over the chunks per step."""

            def select0(c, carry):
                s = sl(c)
                return select(c * CH, a0_ref[s], g0_ref[s], y_ref[s], c_ref[s], carry)

            gmax, i, m2 = jax.lax.fori_loop(0, nch, select0, sel0)
            sync()

            def body(carry):
                it, _, i, gmax, _ = carry
                xi = point(i)
                ai, yi, ci = al_ref[i], y_ref[i], c_ref[i]

                def sweep_b(c, car):
                    s = sl(c)
                    return second_order(c * CH, al_ref[s], g_ref[s], y_ref[s], c_ref[s],
                                        krow(xrows_at(s), xi), gmax, car)

                best, j = jax.lax.fori_loop(0, nch, sweep_b, (f32(NEG), jnp.int32(0)))
                found = finite(best)
                xj = point(j)
                t, new_ai, new_aj = pair_step(found, gmax, xi, xj, ai, yi, ci,
                                              al_ref[j], g_ref[j], y_ref[j], c_ref[j])
                sync()

                def sweep_a(c, car):  # apply the step, then select the next i
                    s = sl(c)
                    slot = c * CH + lane
                    al, G, yv, cv = al_ref[s], g_ref[s], y_ref[s], c_ref[s]
                    al = jnp.where(slot == j, new_aj, jnp.where(slot == i, new_ai, al))
                    xr = xrows_at(s)
                    G = G + (yv * t) * (krow(xr, xi) - krow(xr, xj))
                    al_ref[s] = al
                    g_ref[s] = G
                    return select(c * CH, al, G, yv, cv, car)

                gmax, i, m2 = jax.lax.fori_loop(0, nch, sweep_a, sel0)
                sync()
                gap = gmax + m2
                return it + found.astype(jnp.int32), (~found) | converged(gap), i, gmax, gap

            gap = gmax + m2
            init = (jnp.int32(0), converged(gap), i, gmax, gap)
            it, _, _, _, gap = jax.lax.while_loop(cond, body, init)
            return it, gap

        def in_registers():
            """At most ``resident`` points: α, G and the points stay in registers, ``steps`` SMO
            steps at a time (a finished problem's extra steps are no-ops); α and G go through
            global memory only between two such blocks (Triton carries tensors through counted
            loops, not through data-dependent ones)."""
            s = pl.ds(0, resident)
            lane_r = jax.lax.broadcasted_iota(jnp.int32, (resident,), 0)
            yv, cv, xr = y_ref[s], c_ref[s], xrows_at(s)

            def at(v, k):  # v[k] of a register vector (exact: one nonzero term)
                return jnp.sum(jnp.where(lane_r == k, v, 0.0))

            def step(_, carry):
                it, done, i, gmax, gap, al, G = carry
                live = (~done) & (it < max_iter)
                xi = point(i)
                Ki = krow(xr, xi)
                best, j = second_order(0, al, G, yv, cv, Ki, gmax, (f32(NEG), jnp.int32(0)))
                found = finite(best)
                xj = point(j)
                t, new_ai, new_aj = pair_step(found, gmax, xi, xj, at(al, i), y_ref[i], c_ref[i],
                                              at(al, j), at(G, j), y_ref[j], c_ref[j])
                al2 = jnp.where(lane_r == j, new_aj, jnp.where(lane_r == i, new_ai, al))
                G2 = G + (yv * t) * (Ki - krow(xr, xj))
                gmax2, i2, m2 = select(0, al2, G2, yv, cv, sel0)
                gap2 = gmax2 + m2
                new = (it + found.astype(jnp.int32), (~found) | converged(gap2), i2, gmax2, gap2, al2, G2)
                return tuple(jnp.where(live, b, a) for a, b in zip(carry, new))

            def block(carry):
                out = jax.lax.fori_loop(0, steps, step, carry + (al_ref[s], g_ref[s]))
                al_ref[s] = out[5]
                g_ref[s] = out[6]
                sync()
                return out[:5]

            gmax, i, m2 = select(0, a0_ref[s], g0_ref[s], yv, cv, sel0)
            gap = gmax + m2
            sync()  # the copy above wrote this chunk
            init = (jnp.int32(0), converged(gap), i, gmax, gap)
            it, _, _, _, gap = jax.lax.while_loop(cond, block, init)
            return it, gap

        if resident:
            it, gap = jax.lax.cond(n_act <= resident, in_registers, chunked)
        else:
            it, gap = chunked()
        it_ref[...] = jnp.full((1,), it, jnp.int32)
        gap_ref[...] = jnp.full((1,), gap, f32)

    return kernel


def _solve_pallas(X, y, Cv, alpha0, G0, gamma, tol, max_iter: int, inner: Solver):
    """``_solve`` with the whole SMO loop of the problem in one Pallas kernel program.

    G is exact on the problem's slots (C_i > 0 or α₀_i ≠ 0); other slots return G₀ (they never
    enter the working set and no caller reads their gradient).
    """

    n, d = X.shape
    CH = inner.chunk
    n_pad = -(-n // max(CH, inner.resident)) * max(CH, inner.resident)
    n_chunks = n_pad // CH
    f32 = jnp.float32
    act = (Cv > 0) | (alpha0 != 0)
    n_act = jnp.sum(act, dtype=jnp.int32)
    # stable compaction: the problem's slots first, in slot order (the same tie-breaking as XLA)
    pos = jnp.where(act, jnp.cumsum(act) - 1, n_act + jnp.cumsum(~act) - 1).astype(jnp.int32)
    perm = jnp.zeros((n,), jnp.int32).at[pos].set(jnp.arange(n, dtype=jnp.int32), unique_indices=True)

    def compact(v, fill):
        v = jnp.take(v.astype(f32), perm, axis=-1)
        return jnp.pad(v, [(0, 0)] * (v.ndim - 1) + [(0, n_pad - n)], constant_values=fill)

    args = (compact(X.T, 0.0), compact(y, 1.0), compact(jnp.where(act, Cv, 0.0), 0.0),
            compact(alpha0, 0.0), compact(G0, 0.0), n_act.reshape(1),
            jnp.stack([jnp.asarray(gamma, f32), jnp.asarray(tol, f32)]))
    kwargs = {}
    if not inner.interpret:
        kwargs["compiler_params"] = plgpu.CompilerParams(num_warps=inner.warps, num_stages=1)
    kernel = _smo_kernel(d, CH, n_chunks, int(max_iter), inner.variadic, inner.resident, inner.steps,
                         barrier=not inner.interpret)
    alpha_c, G_c, it, gap = pl.pallas_call(
        kernel,
        out_shape=[jax.ShapeDtypeStruct((n_pad,), f32), jax.ShapeDtypeStruct((n_pad,), f32),
                   jax.ShapeDtypeStruct((1,), jnp.int32), jax.ShapeDtypeStruct((1,), f32)],
        interpret=inner.interpret,
        name="smo",
        **kwargs,
    )(*args)
    alpha = jnp.where(act, alpha_c[pos], alpha0)
    G = jnp.where(act, G_c[pos], G0)
    gap = gap[0]
    gap = jnp.where(jnp.isfinite(gap), gap, 0.0)  # an empty working set is optimal
    return alpha, G, it[0], gap


def _rho(y, Cv, alpha, G, mask):
    """libsvm's calculate_rho: mean y·G over free SVs, else the midpoint of the bounds."""
    yG = y * G
    upper = alpha >= Cv
    lower = alpha <= 0
    free = mask & ~upper & ~lower
    ub_set = mask & ((upper & (y < 0)) | (lower & (y > 0)))
    lb_set = mask & ((upper & (y > 0)) | (lower & (y < 0)))
    ub = jnp.min(jnp.where(ub_set, yG, jnp.inf))
    lb = jnp.max(jnp.where(lb_set, yG, -jnp.inf))
    nfree = jnp.sum(free)
    r_free = jnp.sum(jnp.where(free, yG, 0.0)) / jnp.maximum(nfree, 1)
    fin_ub, fin_lb = jnp.isfinite(ub), jnp.isfinite(lb)
    r_bound = jnp.where(
        fin_ub & fin_lb, 0.5 * (ub + lb), jnp.where(fin_ub, ub, jnp.where(fin_lb, lb, 0.0))
    )
    rho = jnp.where(nfree > 0, r_free, r_bound)
    # no valid point at all: a model that contains nothing
    return jnp.where(jnp.any(mask), rho, 1.0)


# --------------------------------------------------------------------------------------------
# Problem set-up (public: initiation.py sets up both problems and switches between them with
# traced flags)


def svc_problem(labels, mask, C, balanced):
    """(y, C_i, α₀, G₀) of a C-SVC, the problem ``fit_problem`` solves; ``balanced`` may be a
    traced bool."""
    mask = mask.astype(bool)
    pos = mask & (labels > 0)
    neg = mask & ~(labels > 0)
    y = jnp.where(labels > 0, 1.0, -1.0).astype(jnp.float32)
    n = jnp.sum(mask).astype(jnp.float32)
    n_pos = jnp.sum(pos).astype(jnp.float32)
    n_neg = jnp.sum(neg).astype(jnp.float32)
    # scikit-learn's "balanced": n / (n_classes · n_c), with n_classes = 2 for a two-class fit
    w_pos = jnp.where(balanced, n / (2.0 * jnp.maximum(n_pos, 1.0)), 1.0)
    w_neg = jnp.where(balanced, n / (2.0 * jnp.maximum(n_neg, 1.0)), 1.0)
    Cv = jnp.where(pos, C * w_pos, jnp.where(neg, C * w_neg, 0.0)).astype(jnp.float32)
    alpha0 = jnp.zeros_like(Cv)
    G0 = jnp.full_like(Cv, -1.0)
    return y, Cv, alpha0, G0


def _one_class_alpha0(mask, nu):
    """libsvm's start: first ⌊ν·l⌋ valid points at 1, the next at ν·l − ⌊ν·l⌋."""
    mask = mask.astype(bool)
    rank = jnp.cumsum(mask) - 1
    nul = nu * jnp.sum(mask).astype(jnp.float32)
    return jnp.where(mask, jnp.clip(nul - rank.astype(jnp.float32), 0.0, 1.0), 0.0)


def one_class_start_bound(nu, n_slots: int) -> int:
    """Static bound on libsvm's nonzero starting alphas (⌈ν·l⌉ ≤ ⌊ν·n⌋ + 1), or n when ν is traced."""
    v = _concrete(nu)
    if v is None or v.ndim != 0:
        return n_slots
    return int(min(n_slots, np.floor(float(v) * n_slots) + 2))


def one_class_problem(X, mask, nu, gamma, start_bound=None):
    """(y, C_i, α₀, G₀ = Kα₀) of a one-class ν-SVM.

    ``start_bound`` (static): at most this many nonzero α₀ (see ``one_class_start_bound``), so
    G₀ costs start_bound × n kernel values instead of n × n.
    """
    mask = mask.astype(bool)
    n = mask.shape[0]
    y = jnp.ones(mask.shape, jnp.float32)
    Cv = mask.astype(jnp.float32)
    alpha0 = _one_class_alpha0(mask, nu)
    if start_bound is None or start_bound >= n:
        G0 = _kernel_sum(X, alpha0, X, gamma)
    else:
        (idx,) = jnp.nonzero(alpha0 > 0, size=start_bound, fill_value=0)
        used = jnp.arange(start_bound) < jnp.sum(alpha0 > 0)
        G0 = _kernel_sum(X[idx], jnp.where(used, alpha0[idx], 0.0), X, gamma)
    return y, Cv, alpha0, G0


def fit_problem(X, mask, problem, one_class, gamma, tol, max_iter, inner):
    """Solve a set-up problem. Returns (model, training decision values f(X))."""
    y, Cv, alpha0, G0 = problem
    alpha, G, n_iter, gap = _solve(X, y, Cv, alpha0, G0, gamma, tol, max_iter, inner)
    mask = mask.astype(bool)
    alpha = jnp.where(mask, alpha, 0.0)
    rho = _rho(y, Cv, alpha, G, mask).astype(jnp.float32)
    model = SVMModel(
        support=X,
        coef=y * alpha,
        rho=rho,
        gamma=jnp.asarray(gamma, jnp.float32),
        mask=mask,
        one_class=jnp.asarray(one_class, bool),
        converged=gap < tol,
        n_iter=n_iter,
        gap=gap.astype(jnp.float32),
    )
    # G = Qα + p, so Σ_j coef_j K_ij = y_i (G_i − p_i): the training decisions come for free
    p = jnp.where(one_class, 0.0, -1.0)
    return model, y * (G - p) - rho


def clean_points(X, mask):
    """float32 points with padded slots zeroed (whatever they held, NaN included)."""
    return jnp.where(mask.astype(bool)[:, None], X.astype(jnp.float32), 0.0)


@functools.partial(jax.jit, static_argnames=("max_iter", "inner"))
def _fit_svc_jit(X, labels, mask, gamma, C, balanced, tol, max_iter, inner):
    X = clean_points(X, mask)
    problem = svc_problem(labels, mask, jnp.asarray(C, jnp.float32), balanced)
    return fit_problem(X, mask, problem, False, gamma, tol, max_iter, inner)[0]


@functools.partial(jax.jit, static_argnames=("max_iter", "inner", "start_bound"))
def _fit_one_class_jit(X, mask, nu, gamma, tol, max_iter, inner, start_bound):
    X = clean_points(X, mask)
    problem = one_class_problem(X, mask, jnp.asarray(nu, jnp.float32), gamma, start_bound)
    return fit_problem(X, mask, problem, True, gamma, tol, max_iter, inner)[0]


# --------------------------------------------------------------------------------------------
# Public API


def fit_svc(X, labels, mask, *, gamma, C=1.0, class_weight=None, tol=1e-3, max_iter=None,
            backend="auto", _inner=None) -> SVMModel:
    """Fit a two-class RBF C-SVC (scikit-learn ``SVC(kernel="rbf", gamma, C, class_weight, tol)``).

    X: (n, d) points (padded slots anywhere); labels: (n,) 1 = positive, 0 = negative;
    mask: (n,) bool, True on valid slots. gamma > 0, C > 0, tol > 0 may be traced.
    class_weight: None, "balanced" (w_c = n / (2 n_c)), or a (traced) bool scalar choosing
    balanced weights at run time. max_iter: SMO step cap (static), default
    ``max(10_000, 4 n)``; check ``model.converged``. backend: "auto" (the fused Pallas kernel on
    GPUs, the XLA loop elsewhere), "xla" or "pallas" (off a GPU: interpret mode, slow; for tests).

    With a single class present (scikit-learn raises) the result is the constant classifier of
    that class: all α = 0 and ``f ≡ +1`` (only positives) or ``f ≡ −1`` (only negatives); with
    no valid point at all ``f ≡ −1``. Callers wanting DSC's behaviour fit a one-class SVM instead.
    Jit- and vmap-able; different valid counts at the same padded size never retrace.
    """
    _check_points(X, mask, labels)
    _check_range("gamma", gamma, 0.0, None)
    _check_range("C", C, 0.0, None)
    _check_range("tol", tol, 0.0, None)
    if class_weight is None:
        balanced = False
    elif isinstance(class_weight, str):
        if class_weight != "balanced":
            raise ValueError(f"class_weight must be None, 'balanced' or a bool, got {class_weight!r}")
        balanced = True
    elif isinstance(class_weight, dict):
        raise ValueError("class_weight dicts are not supported; use None, 'balanced' or a bool")
    else:
        balanced = jnp.asarray(class_weight, bool)
        if balanced.shape != ():
            raise ValueError(f"a class_weight switch must be a scalar bool, got shape {balanced.shape}")
    max_iter = check_max_iter(max_iter, X.shape[0])
    return _fit_svc_jit(X, labels, mask, gamma, C, balanced, tol, max_iter=max_iter,
                        inner=resolve_inner(_inner, backend))


def fit_one_class(X, mask, *, nu, gamma, tol=1e-3, max_iter=None, backend="auto",
                  _inner=None) -> SVMModel:
    """Fit an RBF one-class ν-SVM (scikit-learn ``OneClassSVM(kernel="rbf", nu, gamma, tol)``).

    X: (n, d) points; mask: (n,) bool valid slots; nu in (0, 1], gamma > 0 (both may be traced).
    ν·l < 1 is fine (a single fractional α). With no valid point the model contains nothing.
    ``decision_function`` equals scikit-learn's (ρ = its ``offset_``); inside iff f > 0.
    max_iter and backend as in ``fit_svc``.
    """
    _check_points(X, mask)
    _check_range("nu", nu, 0.0, 1.0)
    _check_range("gamma", gamma, 0.0, None)
    _check_range("tol", tol, 0.0, None)
    max_iter = check_max_iter(max_iter, X.shape[0])
    return _fit_one_class_jit(X, mask, nu, gamma, tol, max_iter=max_iter, inner=resolve_inner(_inner, backend),
                              start_bound=one_class_start_bound(nu, X.shape[0]))


def decision_function(model: SVMModel, X_query) -> jax.Array:
    """f(x) = Σ coef_i K(support_i, x) − ρ for (q, d) or (d,) queries; positive = inside."""
    Xq = jnp.asarray(X_query, jnp.float32)
    d = model.support.shape[-1]
    if Xq.shape[-1] != d:
        raise ValueError(f"queries must have {d} features (last axis), got shape {Xq.shape}")
    single = Xq.ndim == 1
    Xq2 = Xq.reshape(-1, d)
    f = _kernel_sum(model.support, model.coef, Xq2, model.gamma) - model.rho
    return f[0] if single else f.reshape(Xq.shape[:-1])


def predict(model: SVMModel, X_query) -> jax.Array:
    """Inside/positive as scikit-learn decides: f ≥ 0 for a C-SVC, f > 0 for a one-class SVM."""
    f = decision_function(model, X_query)
    return jnp.where(model.one_class, f > 0, f >= 0)

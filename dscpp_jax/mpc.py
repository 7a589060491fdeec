"""Random-shooting model predictive control with a terminal value (paper eq. 2).

For each environment: draw M action sequences of length K uniformly in [-1, 1]^A, roll each through
the learned dynamics, and score it with

    cost = sum_{j=0..K-1} gamma^j * c_j  -  gamma^K * V(s_K, g),
    c_j  = 1 if ||xy(s_{j+1}) - g|| > tolerance else 0,

where V(s, g) = min(Q1, Q2)(s, g, pi(s, g)) is supplied by the caller as ``value_fn``. As in the
original code, sequences whose final predicted state is already within tolerance of the goal get the
largest V of that environment's batch. The first action of the cheapest sequence is executed.
``use_value=False`` drops the V term (the flat finite-horizon baseline of Nagabandi et al.).

Two interchangeable back ends compute the rollouts:
- ``"xla"``: plain JAX; all environments' sequences form one (envs * M)-row matmul chain. float32 or
  bfloat16 operands (float32 accumulation, float32 state).
- ``"pallas"``: one fused GPU kernel (Pallas/Triton) per (env, block of sequences) that keeps the
  whole K-step rollout of a block on chip (bf16 operands, float32 accumulation and state): only the
  actions go in and the discounted step costs and final states come out. ``"auto"`` picks it on a
  GPU for the paper's 2-hidden-layer model, else ``"xla"``.

Ensemble members enter as the mean prediction of all members at each step (``ensemble_mode="mean"``,
the default: E times the work) or one member per sequence (``"member"``: sequence i is rolled out by
member (i // block_rows) % E for all K steps, at the cost of a single model). Measured on the ant
(experiments/results/mpc_evidence.md): the mean picks better sequences under the true dynamics, one
member per sequence does not beat a single model, and bf16 operands pick as well as float32.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from dscpp_jax.dynamics import DynamicsConfig, DynamicsState, FoldedDynamics, dynamics_fold

__all__ = [
    "MPCConfig",
    "mpc_cost",
    "sample_action_sequences",
    "rollout_xy",
    "sequence_costs",
    "mpc_action",
    "mpc_actions",
    "shooting_actions",
    "mpc_flops_per_decision",
]

_DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


@dataclasses.dataclass(frozen=True)
class MPCConfig:
    """Static settings of the random-shooting controller.

    num_samples: M action sequences per decision (paper: 14,000).
    horizon: K actions per sequence (paper: 7).
    discount: gamma of eq. 2 (original: 0.95).
    goal_tolerance: distance under which a predicted xy counts as at the goal (0.6).
    use_value: add the terminal value term (False = flat finite-horizon MPC).
    compute_dtype: "float32" or "bfloat16" matmul operands (accumulation and state stay float32).
    ensemble_mode: "mean" (mean of members at each step; measured better, E times the work) or
        "member" (one member per sequence). Identical for a single model.
    backend: "auto", "xla" or "pallas" (the fused GPU kernel; bfloat16 only).
    block_rows, num_warps, num_stages, hidden_chunk, out_chunk: tiling of the fused kernel (rows per
        program, warps, pipelining stages, first-layer and second-layer hidden blocks).
    value_precision: matmul precision of the value_fn call (None = JAX default; "bfloat16" runs the
        critic's float32 matmuls as single bf16 passes).
    """

    num_samples: int = 14000
    horizon: int = 7
    discount: float = 0.95
    goal_tolerance: float = 0.6
    use_value: bool = True
    compute_dtype: str = "bfloat16"
    ensemble_mode: str = "mean"
    backend: str = "auto"
    block_rows: int = 64
    num_warps: int = 4
    num_stages: int = 1
    hidden_chunk: int = 128
    out_chunk: int = 64
    value_precision: Optional[str] = None

    def __post_init__(self):
        if self.num_samples < 1 or self.horizon < 1:
            raise ValueError(f"num_samples and horizon must be >= 1, got {self.num_samples}, {self.horizon}")
        if not 0.0 < self.discount <= 1.0:
            raise ValueError(f"discount must be in (0, 1], got {self.discount}")
        if self.compute_dtype not in _DTYPES:
            raise ValueError(f"compute_dtype must be one of {list(_DTYPES)}, got {self.compute_dtype!r}")
        if self.ensemble_mode not in ("member", "mean"):
            raise ValueError(f"ensemble_mode must be 'member' or 'mean', got {self.ensemble_mode!r}")
        if self.backend not in ("auto", "xla", "pallas"):
            raise ValueError(f"backend must be 'auto', 'xla' or 'pallas', got {self.backend!r}")
        for name in ("block_rows", "hidden_chunk", "out_chunk"):
            v = getattr(self, name)
            if v < 16 or v & (v - 1):
                raise ValueError(f"{name} must be a power of 2 >= 16, got {v}")
        if self.out_chunk > self.hidden_chunk or self.hidden_chunk % self.out_chunk:
            raise ValueError(f"out_chunk ({self.out_chunk}) must divide hidden_chunk ({self.hidden_chunk})")


def mpc_flops_per_decision(mpc_cfg: MPCConfig, obs_dim: int, action_dim: int,
                           hidden=(500, 500)) -> float:
    """Multiply-add FLOPs (2 per MAC) of the dynamics rollouts of one decision (value net excluded)."""
    dims = (obs_dim + action_dim,) + tuple(hidden) + (obs_dim,)
    macs = sum(a * b for a, b in zip(dims[:-1], dims[1:]))
    return 2.0 * macs * mpc_cfg.num_samples * mpc_cfg.horizon


# --------------------------------------------------------------------------------------------
# Eq. 2 cost (pure, backend independent)
# --------------------------------------------------------------------------------------------

def _discounts(mpc_cfg: MPCConfig):
    return mpc_cfg.discount ** np.arange(mpc_cfg.horizon, dtype=np.float64)


def _terminal(mpc_cfg: MPCConfig, step_cost, final_at_goal, final_values, valid=None):
    """step_cost (..., M) + terminal term; the at-goal rule uses the max V over valid sequences."""
    if final_values is None:
        return step_cost
    v = final_values.astype(jnp.float32)
    vm = v if valid is None else jnp.where(valid, v, -jnp.inf)
    vmax = jnp.max(vm, axis=-1, keepdims=True)
    v = jnp.where(final_at_goal, vmax, v)
    return step_cost - jnp.float32(mpc_cfg.discount ** mpc_cfg.horizon) * v


def mpc_cost(mpc_cfg: MPCConfig, pred_xy, goal, final_values=None):
    """Eq. 2 cost of each sequence from its predicted positions.

    pred_xy (..., M, K, 2): xy of the predicted states s_1..s_K; goal (..., 2); final_values
    (..., M) = V(s_K, g) or None (no terminal term). Returns (..., M) costs (lower is better).
    """
    pred_xy = jnp.asarray(pred_xy, jnp.float32)
    if pred_xy.shape[-2] != mpc_cfg.horizon or pred_xy.shape[-1] != 2:
        raise ValueError(f"pred_xy must be (..., M, K={mpc_cfg.horizon}, 2), got {pred_xy.shape}")
    goal = jnp.asarray(goal, jnp.float32)[..., None, None, :]
    d2 = jnp.sum(jnp.square(pred_xy - goal), -1)  # (..., M, K)
    far = d2 > jnp.float32(mpc_cfg.goal_tolerance) ** 2
    step_cost = jnp.sum(far.astype(jnp.float32) * jnp.asarray(_discounts(mpc_cfg), jnp.float32), -1)
    if not mpc_cfg.use_value:
        final_values = None
    return _terminal(mpc_cfg, step_cost, ~far[..., -1], final_values)


# --------------------------------------------------------------------------------------------
# Rollouts (XLA back end)
# --------------------------------------------------------------------------------------------

def sample_action_sequences(key, mpc_cfg: MPCConfig, num_envs: int, action_dim: int):
    """Uniform action sequences (num_envs, M, K, A) in [-1, 1]."""
    return jax.random.uniform(key, (num_envs, mpc_cfg.num_samples, mpc_cfg.horizon, action_dim),
                              jnp.float32, -1.0, 1.0)


def _leaky(x, slope):
    return jnp.maximum(x, slope * x) if slope <= 1.0 else jnp.where(x > 0, x, slope * x)


def _member_step(fd: FoldedDynamics, e, s, a, slope, cdt):
    """One folded-model step of member e on rows s (..., obs), a (..., A)."""
    def mm(x, w):
        return jnp.dot(x.astype(cdt), w.astype(cdt), preferred_element_type=jnp.float32)

    h = _leaky(mm(s, fd.w_s[e]) + mm(a, fd.w_a[e]) + fd.b_in[e], slope)
    for w, b in zip(fd.w_hidden, fd.b_hidden):
        h = _leaky(mm(h, w[e]) + b[e], slope)
    return s + mm(h, fd.w_out[e]) + fd.b_out[e]


def _rollout_xla(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, fd: FoldedDynamics, obs, actions):
    """obs (B, obs), actions (B, M, K, A) -> (xy (B, M, K, 2), final states (B, M, obs))."""
    cdt = _DTYPES[mpc_cfg.compute_dtype]
    slope = dyn_cfg.negative_slope
    B, M, K, A = actions.shape
    E = fd.w_s.shape[0]
    s0 = jnp.broadcast_to(obs[:, None, :].astype(jnp.float32), (B, M, obs.shape[-1]))
    acts = jnp.moveaxis(actions, 2, 0)  # (K, B, M, A)

    if E == 1:
        step = lambda s, a: _member_step(fd, 0, s, a, slope, cdt)
    elif mpc_cfg.ensemble_mode == "mean":
        def step(s, a):
            return jax.vmap(lambda e: _member_step(fd, e, s, a, slope, cdt))(jnp.arange(E)).mean(0)
    else:  # one member per sequence: block j of block_rows sequences uses member j % E
        BM = mpc_cfg.block_rows
        nbp = -(-(-(-M // BM)) // E) * E  # blocks, rounded up to a multiple of E
        pad = nbp * BM - M

        def step(s, a):
            sp = jnp.pad(s, ((0, 0), (0, pad), (0, 0))).reshape(B, nbp // E, E, BM, -1)
            ap = jnp.pad(a, ((0, 0), (0, pad), (0, 0))).reshape(B, nbp // E, E, BM, -1)
            out = jax.vmap(lambda e, si, ai: _member_step(fd, e, si, ai, slope, cdt),
                           in_axes=(0, 2, 2), out_axes=2)(jnp.arange(E), sp, ap)
            return out.reshape(B, nbp * BM, -1)[:, :M]

    def body(s, a):
        s = step(s, a)
        return s, s[..., :2]

    final, xy = jax.lax.scan(body, s0, acts)
    return jnp.moveaxis(xy, 0, 2), final


def rollout_xy(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, obs, actions):
    """Predicted xy of s_1..s_K (B, M, K, 2) and final states (B, M, obs) for given sequences
    (XLA back end; the reference the fused kernel is tested against)."""
    fd = dynamics_fold(dyn_cfg, dyn_state)
    return _rollout_xla(mpc_cfg, dyn_cfg, fd, jnp.asarray(obs, jnp.float32), jnp.asarray(actions, jnp.float32))


# --------------------------------------------------------------------------------------------
# Fused rollout kernel (Pallas, Triton on GPU)
# --------------------------------------------------------------------------------------------

def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def _pad_to(x, shape):
    return jnp.pad(x, [(0, t - s) for s, t in zip(x.shape, shape)])


def _kernel_weights(fd: FoldedDynamics, SP, AP, HP):
    E = fd.w_s.shape[0]
    bf = jnp.bfloat16
    ws = _pad_to(fd.w_s, (E, SP, HP)).astype(bf)
    wa = _pad_to(fd.w_a, (E, AP, HP)).astype(bf)
    b1 = _pad_to(fd.b_in, (E, HP)).astype(jnp.float32)[:, None, :]
    w2 = _pad_to(fd.w_hidden[0], (E, HP, HP)).astype(bf)
    b2 = _pad_to(fd.b_hidden[0], (E, HP)).astype(jnp.float32)[:, None, :]
    w3 = _pad_to(fd.w_out, (E, HP, SP)).astype(bf)
    b3 = _pad_to(fd.b_out, (E, SP)).astype(jnp.float32)[:, None, :]
    return ws, wa, b1, w2, b2, w3, b3


def _kernel_dims(mpc_cfg: MPCConfig, obs_dim, act_dim, hidden):
    SP = max(16, _pow2(obs_dim))
    AP = max(16, _pow2(act_dim))
    HP = max(mpc_cfg.hidden_chunk, -(-hidden // mpc_cfg.hidden_chunk) * mpc_cfg.hidden_chunk)
    BM = mpc_cfg.block_rows
    Mp = -(-mpc_cfg.num_samples // BM) * BM
    return SP, AP, HP, BM, Mp


def _rollout_pallas(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, fd: FoldedDynamics, obs, goal, acts_k,
                    interpret: bool = False):
    """Fused K-step rollout.

    obs (B, obs), goal (B, 2), acts_k (B, K, Mp, AP) bf16 (kernel layout, zero padding lanes).
    Returns (discounted step-cost sums (B, Mp), final states (B, Mp, SP) float32).
    """
    from jax.experimental import pallas as pl

    B, obs_dim = obs.shape
    E = fd.w_s.shape[0]
    act_dim = fd.w_a.shape[1]
    hidden = fd.w_s.shape[2]
    SP, AP, HP, BM, Mp = _kernel_dims(mpc_cfg, obs_dim, act_dim, hidden)
    K = mpc_cfg.horizon
    CH = mpc_cfg.hidden_chunk
    NC = mpc_cfg.out_chunk
    nH = HP // CH
    slope = float(dyn_cfg.negative_slope)
    gamma = float(mpc_cfg.discount)
    tol2 = float(mpc_cfg.goal_tolerance) ** 2
    f32, bf = jnp.float32, jnp.bfloat16
    if acts_k.shape != (B, K, Mp, AP):
        raise ValueError(f"kernel actions must be {(B, K, Mp, AP)}, got {acts_k.shape}")

    ws, wa, b1, w2, b2, w3, b3 = _kernel_weights(fd, SP, AP, HP)
    s0 = _pad_to(obs.astype(f32), (B, SP))
    g = _pad_to(goal.astype(f32), (B, SP))

    def leaky(x):
        return jnp.maximum(x, slope * x)

    mean_mode = mpc_cfg.ensemble_mode == "mean" and E > 1
    if mean_mode:  # every program loops over all members: the output layer's bias is averaged once
        b3 = jnp.broadcast_to(b3.mean(0, keepdims=True), b3.shape)

    def kernel(s0_ref, g_ref, a_ref, ws_ref, wa_ref, b1_ref, w2_ref, b2_ref, w3_ref, b3_ref,
               cost_ref, sk_ref):
        s = jnp.broadcast_to(s0_ref[...], (BM, SP))
        gg = g_ref[...]
        lane = jax.lax.broadcasted_iota(jnp.int32, (1, SP), 1)
        xy_lane = lane < 2

        def W(ref, e, *idx):  # a weight tile of member e (member mode: the block is one member)
            return ref[(e,) + idx] if mean_mode else ref[idx]

        def member_delta(e, sb, a):
            h1 = []
            for k in range(nH):
                acc = jnp.dot(sb, W(ws_ref, e, slice(None), pl.ds(k * CH, CH)), preferred_element_type=f32)
                acc = acc + jnp.dot(a, W(wa_ref, e, slice(None), pl.ds(k * CH, CH)), preferred_element_type=f32)
                acc = acc + W(b1_ref, e, slice(None), pl.ds(k * CH, CH))
                h1.append(leaky(acc).astype(bf))

            # Layer 2 and the output layer, one block of NC hidden units at a time. The loop is a
            # real loop whose weight loads depend on its index, so the compiler cannot hoist all
            # weight tiles out of the K-step loop (they would not fit in shared memory).
            def out_chunk(c, ds):
                c0 = pl.multiple_of(c * NC, NC)
                acc = jnp.dot(h1[0], W(w2_ref, e, pl.ds(0, CH), pl.ds(c0, NC)), preferred_element_type=f32)
                for k in range(1, nH):
                    acc = acc + jnp.dot(h1[k], W(w2_ref, e, pl.ds(k * CH, CH), pl.ds(c0, NC)),
                                        preferred_element_type=f32)
                acc = acc + W(b2_ref, e, slice(None), pl.ds(c0, NC))
                h2 = leaky(acc).astype(bf)
                return ds + jnp.dot(h2, W(w3_ref, e, pl.ds(c0, NC), slice(None)), preferred_element_type=f32)

            return jax.lax.fori_loop(0, HP // NC, out_chunk, jnp.zeros((BM, SP), f32))

        def step(t, carry):
            s, cost, disc = carry
            a = a_ref[t]  # (BM, AP) bf16
            sb = s.astype(bf)
            if mean_mode:
                ds = jax.lax.fori_loop(0, E, lambda e, acc: acc + member_delta(e, sb, a),
                                       jnp.zeros((BM, SP), f32)) * (1.0 / E)
                s = s + ds + W(b3_ref, 0, slice(None), slice(None))
            else:
                s = s + member_delta(0, sb, a) + b3_ref[...]
            d2 = jnp.sum(jnp.where(xy_lane, jnp.square(s - gg), 0.0), axis=1)
            cost = cost + disc * (d2 > tol2).astype(f32)
            return s, cost, disc * gamma

        s, cost, _ = jax.lax.fori_loop(0, K, step, (s, jnp.zeros((BM,), f32), jnp.float32(1.0)))
        cost_ref[...] = cost[None, :]
        sk_ref[...] = s

    nb = Mp // BM
    def wspec(shape):
        if mean_mode:  # all members in every program
            return pl.BlockSpec((E,) + shape, lambda b, i: (0, 0, 0))
        return pl.BlockSpec((None,) + shape, lambda b, i: (i % E, 0, 0))

    in_specs = [
        pl.BlockSpec((1, SP), lambda b, i: (b, 0)),
        pl.BlockSpec((1, SP), lambda b, i: (b, 0)),
        pl.BlockSpec((None, K, BM, AP), lambda b, i: (b, 0, i, 0)),
        wspec((SP, HP)), wspec((AP, HP)), wspec((1, HP)), wspec((HP, HP)), wspec((1, HP)),
        wspec((HP, SP)), wspec((1, SP)),
    ]
    out_specs = [
        pl.BlockSpec((1, BM), lambda b, i: (b, i)),
        pl.BlockSpec((None, BM, SP), lambda b, i: (b, i, 0)),
    ]
    kwargs = {}
    if not interpret:
        from jax.experimental.pallas import triton as plgpu
        kwargs["compiler_params"] = plgpu.CompilerParams(num_warps=mpc_cfg.num_warps,
                                                         num_stages=mpc_cfg.num_stages)
    flops = int(2 * B * Mp * K * (SP * HP + AP * HP + HP * HP + HP * SP) * (E if mean_mode else 1))
    cost, sk = pl.pallas_call(
        kernel,
        grid=(B, nb),
        in_specs=in_specs,
        out_specs=out_specs,
        out_shape=[jax.ShapeDtypeStruct((B, Mp), f32), jax.ShapeDtypeStruct((B, Mp, SP), f32)],
        interpret=interpret,
        cost_estimate=pl.CostEstimate(flops=flops, transcendentals=0,
                                      bytes_accessed=int(B * Mp * (K * AP * 2 + SP * 4 + 4))),
        name="mpc_rollout",
        **kwargs,
    )(s0, g, acts_k, ws, wa, b1, w2, b2, w3, b3)
    return cost, sk


def _to_kernel_layout(mpc_cfg: MPCConfig, actions, AP, Mp):
    """(B, M, K, A) float -> (B, K, Mp, AP) bf16 with zero padding."""
    a = jnp.moveaxis(actions, 2, 1).astype(jnp.bfloat16)
    return _pad_to(a, a.shape[:2] + (Mp, AP))


# --------------------------------------------------------------------------------------------
# Decisions
# --------------------------------------------------------------------------------------------

def _resolve_backend(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig) -> str:
    if mpc_cfg.backend != "auto":
        return mpc_cfg.backend
    ok = (jax.default_backend() == "gpu" and len(dyn_cfg.hidden) == 2
          and mpc_cfg.compute_dtype == "bfloat16")
    return "pallas" if ok else "xla"


def _check_pallas(mpc_cfg, dyn_cfg):
    if len(dyn_cfg.hidden) != 2:
        raise ValueError(f"backend='pallas' supports 2 hidden layers, got hidden={dyn_cfg.hidden}")
    if mpc_cfg.compute_dtype != "bfloat16":
        raise ValueError("backend='pallas' computes in bfloat16: set compute_dtype='bfloat16' or backend='xla'")


def _values(value_fn, final_states, goal, precision=None):
    """vmap the caller's value_fn(states (M, obs), goal (2,)) -> (M,) over environments."""
    if precision is None:
        v = jax.vmap(value_fn)(final_states, goal)
    else:
        with jax.default_matmul_precision(precision):
            v = jax.vmap(value_fn)(final_states, goal)
    if v.shape != final_states.shape[:2]:
        raise ValueError(f"value_fn must return (M,) values per env, got {v.shape[1:]} for "
                         f"states {final_states.shape[1:]}")
    return v


def sequence_costs(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, obs, goal, actions,
                   value_fn: Optional[Callable] = None, interpret: bool = False):
    """Eq. 2 cost (B, M) of given sequences actions (B, M, K, A) from obs (B, obs) towards goal (B, 2)."""
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    actions = jnp.asarray(actions, jnp.float32)
    if mpc_cfg.use_value and value_fn is None:
        raise ValueError("use_value=True needs a value_fn(states, goal); pass one or set use_value=False")
    backend = _resolve_backend(mpc_cfg, dyn_cfg) if not interpret else "pallas"
    B, M = actions.shape[:2]
    if backend == "xla":
        fd = dynamics_fold(dyn_cfg, dyn_state)
        xy, final = _rollout_xla(mpc_cfg, dyn_cfg, fd, obs, actions)
        v = _values(value_fn, final, goal, mpc_cfg.value_precision) if mpc_cfg.use_value else None
        return mpc_cost(mpc_cfg, xy, goal, v)
    _check_pallas(mpc_cfg, dyn_cfg)
    fd = dynamics_fold(dyn_cfg, dyn_state, jnp.bfloat16)
    SP, AP, HP, BM, Mp = _kernel_dims(mpc_cfg, obs.shape[-1], actions.shape[-1], fd.w_s.shape[2])
    acts_k = _to_kernel_layout(mpc_cfg, actions, AP, Mp)
    return _finish_pallas(mpc_cfg, fd, obs, goal, acts_k, value_fn, M, dyn_cfg, interpret)[0]


def _finish_pallas(mpc_cfg, fd, obs, goal, acts_k, value_fn, M, dyn_cfg, interpret=False):
    step_cost, sk = _rollout_pallas(mpc_cfg, dyn_cfg, fd, obs, goal, acts_k, interpret=interpret)
    step_cost = step_cost[:, :M]
    final = sk[:, :M, :obs.shape[-1]]
    if mpc_cfg.use_value:
        v = _values(value_fn, final, goal, mpc_cfg.value_precision)
        at_goal = jnp.sum(jnp.square(final[..., :2] - goal[:, None, :]), -1) <= jnp.float32(mpc_cfg.goal_tolerance) ** 2
        return _terminal(mpc_cfg, step_cost, at_goal, v), final
    return step_cost, final


def mpc_actions(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, key, obs, goal,
                value_fn: Optional[Callable] = None, return_info: bool = False):
    """MPC decisions for a batch of environments: obs (B, obs), goal (B, 2) -> actions (B, A).

    One key draws all environments' sequences. value_fn(states (M, obs), goal (2,)) -> (M,) is
    vmapped over environments (required when use_value=True). With return_info, also returns a dict
    with the chosen sequence's cost ("cost", (B,)) and index ("index", (B,)).
    """
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    if obs.ndim != 2 or goal.shape != (obs.shape[0], 2):
        raise ValueError(f"obs must be (B, obs_dim) and goal (B, 2), got {obs.shape} and {goal.shape}")
    if mpc_cfg.use_value and value_fn is None:
        raise ValueError("use_value=True needs a value_fn(states, goal); pass one or set use_value=False")
    act_dim = dyn_state.norm.act_mean.shape[0]
    B, M, K = obs.shape[0], mpc_cfg.num_samples, mpc_cfg.horizon
    backend = _resolve_backend(mpc_cfg, dyn_cfg)
    if backend == "xla":
        actions = sample_action_sequences(key, mpc_cfg, B, act_dim)
        fd = dynamics_fold(dyn_cfg, dyn_state)
        xy, final = _rollout_xla(mpc_cfg, dyn_cfg, fd, obs, actions)
        v = _values(value_fn, final, goal, mpc_cfg.value_precision) if mpc_cfg.use_value else None
        cost = mpc_cost(mpc_cfg, xy, goal, v)
        first = actions[:, :, 0, :]
    else:
        _check_pallas(mpc_cfg, dyn_cfg)
        fd = dynamics_fold(dyn_cfg, dyn_state, jnp.bfloat16)
        SP, AP, HP, BM, Mp = _kernel_dims(mpc_cfg, obs.shape[-1], act_dim, fd.w_s.shape[2])
        # Draw directly in the kernel layout (rows past M are never chosen).
        a = jax.random.uniform(key, (B, K, Mp, act_dim), jnp.float32, -1.0, 1.0).astype(jnp.bfloat16)
        acts_k = _pad_to(a, (B, K, Mp, AP))
        cost, _ = _finish_pallas(mpc_cfg, fd, obs, goal, acts_k, value_fn, M, dyn_cfg)
        first = a[:, 0, :M, :].astype(jnp.float32)
    idx = jnp.argmin(cost, axis=-1)
    best = jnp.take_along_axis(first, idx[:, None, None], axis=1)[:, 0, :]
    if return_info:
        return best, {"cost": jnp.take_along_axis(cost, idx[:, None], 1)[:, 0], "index": idx}
    return best


def mpc_action(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, key, obs, goal,
               value_fn: Optional[Callable] = None):
    """One environment's MPC decision: obs (obs_dim,), goal (2,) -> action (A,).

    Same as ``mpc_actions`` on a batch of one with the same key."""
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    if obs.ndim != 1 or goal.shape != (2,):
        raise ValueError(f"obs must be (obs_dim,) and goal (2,), got {obs.shape} and {goal.shape}")
    return mpc_actions(mpc_cfg, dyn_cfg, dyn_state, key, obs[None], goal[None], value_fn)[0]


def shooting_actions(mpc_cfg: MPCConfig, step_fn: Callable, key, obs, goal, action_dim: int,
                     value_fn: Optional[Callable] = None):
    """Random shooting through any batched dynamics ``step_fn(states (N, obs), actions (N, A))``
    (e.g. the true simulator, for tests and oracles). obs (B, obs), goal (B, 2) -> actions (B, A).
    Draws the same sequences as ``mpc_actions(..., backend="xla")`` with the same key."""
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    if mpc_cfg.use_value and value_fn is None:
        raise ValueError("use_value=True needs a value_fn(states, goal); pass one or set use_value=False")
    B, M, K = obs.shape[0], mpc_cfg.num_samples, mpc_cfg.horizon
    actions = sample_action_sequences(key, mpc_cfg, B, action_dim)
    s0 = jnp.broadcast_to(obs[:, None, :], (B, M, obs.shape[-1])).reshape(B * M, -1)

    def body(s, a):
        s = step_fn(s, a.reshape(B * M, -1))
        return s, s[:, :2].reshape(B, M, 2)

    final, xy = jax.lax.scan(body, s0, jnp.moveaxis(actions, 2, 0))
    final = final.reshape(B, M, -1)
    v = _values(value_fn, final, goal, mpc_cfg.value_precision) if mpc_cfg.use_value else None
    cost = mpc_cost(mpc_cfg, jnp.moveaxis(xy, 0, 2), goal, v)
    idx = jnp.argmin(cost, axis=-1)
    return jnp.take_along_axis(actions[:, :, 0, :], idx[:, None, None], axis=1)[:, 0, :]

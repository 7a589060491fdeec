"""Random-shooting model predictive control with a terminal value (paper eq. 2; eq. 1 without it).

For each environment: draw M action sequences of length K uniformly in [-1, 1]^A, roll each through
the learned dynamics, and score it with

    cost = sum_{j=0..K-1} gamma^j * c_j  -  gamma^K * V(s_K, g),
    c_j  = 1 if ||xy(s_{j+1}) - g|| > tolerance else 0,

where V(s, g) = min(Q1, Q2)(s, g, pi(s, g)) is supplied by the caller, either as any callable
``value_fn`` or as the TD3 actor and critic parameters (``value_net``, see ``td3_value_net``). As in the
original code, sequences whose final predicted state is already within tolerance of the goal get the
largest V of that environment's batch. The first action of the cheapest sequence is executed.
``use_value=False`` drops the V term (the flat finite-horizon baseline of Nagabandi et al.).

Two interchangeable back ends compute the rollouts:
- ``"xla"``: plain JAX; all environments' sequences form one (envs * M)-row matmul chain. float32 or
  bfloat16 operands (float32 accumulation, float32 state).
- ``"pallas"``: one fused GPU kernel (Pallas/Triton) per (env, block of sequences) that keeps the
  whole K-step rollout of a block on chip (bf16 operands, float32 accumulation and state). In
  ``mpc_actions`` the kernel also draws the action sequences itself from one seed per environment
  (``kernel_rng``), so no action tensor goes through memory and the chosen first action is recomputed
  from its index; the discounted step costs come out. Given a ``value_net``, the same kernel also
  runs the actor and both critic heads on each block's final states while they are on chip, so only
  V and an at-goal flag come out (``fuse_value``); with a ``value_fn`` the final states are written
  out and V is computed by XLA. ``"auto"`` picks this back end on a GPU for the paper's 2-hidden-layer
  model, else ``"xla"``.

Ensemble members enter as the mean prediction of all members at each step (``ensemble_mode="mean"``,
the default: E times the work) or one member per sequence (``"member"``: sequence i is rolled out by
member (i // block_rows) % E for all K steps, at the cost of a single model). Measured on the ant
(experiments/results/mpc_evidence.md): the mean picks better sequences under the true dynamics, one
member per sequence does not beat a single model, and bf16 operands pick as well as float32; the
fused bf16 value net picks as well as the float32 XLA value (same file).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from dscpp_jax.config import MPCSection
from dscpp_jax.dynamics import DynamicsConfig, DynamicsState, FoldedDynamics, dynamics_fold
from dscpp_jax.networks import Actor, TwinCritic, actor_action_dim

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
    "ValueNet",
    "td3_value_net",
    "value_net_fn",
]

_DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}
_JOIN_MIN_ENVS = 32   # join_input=None: the joined first layer from this many environments up


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
    backend: "auto", "xla" or "pallas" (the fused GPU kernel; bfloat16 only; off a GPU it runs in
        Pallas interpret mode: slow, for tests).
    block_rows, num_warps, num_stages, hidden_chunk, out_chunk: tiling of the fused kernel (rows per
        program, warps, pipelining stages, first-layer and second-layer hidden blocks).
    value_precision: matmul precision of the value_fn call (None = JAX default; "bfloat16" runs the
        critic's float32 matmuls as single bf16 passes).
    fuse_value: with a ``value_net`` and the fused kernel, evaluate the terminal value inside the
        kernel (False: always through XLA after the kernel).
    value_dtype: matmul operands of the fused value net, "bfloat16" or "float32" (TF32 on the GPU,
        like XLA's default float32 matmuls); accumulation in float32 either way.
    value_chunk: hidden block of the fused value net (power of 2 >= 16).
    kernel_rng: in mpc_actions with the fused kernel, draw the action sequences inside the kernel
        (a counter-based hash of one jax.random seed per environment; uniform in [-1, 1) like
        jax.random.uniform) instead of writing them to memory first with jax.random (False).
    join_input: feed state and action to the fused kernel's first layer as one interleaved operand
        (one matmul per hidden block instead of two; same result). None (default): joined from 32
        environments up, where it measured faster on an H200 (6,163 vs 5,961 decisions/s at 256
        environments), and split below (2,080 vs 1,409 at one environment).
    """

    num_samples: int = 14000
    horizon: int = 7
    discount: float = 0.95
    goal_tolerance: float = 0.6
    use_value: bool = True
    compute_dtype: str = "bfloat16"
    ensemble_mode: str = "mean"
    backend: str = "auto"
    block_rows: int = 128
    num_warps: int = 8
    num_stages: int = 2
    hidden_chunk: int = 128
    out_chunk: int = 64
    value_precision: Optional[str] = None
    fuse_value: bool = True
    value_dtype: str = "bfloat16"
    value_chunk: int = 128
    kernel_rng: bool = True
    join_input: Optional[bool] = None

    @classmethod
    def from_section(cls, section: MPCSection, goal_tolerance: float,
                     use_value: bool) -> "MPCConfig":
        """The controller a run config's `mpc` section sets, with the task's goal tolerance and
        whether the learner adds the value term."""
        return cls(num_samples=section.samples, horizon=section.horizon,
                   discount=section.discount, goal_tolerance=goal_tolerance,
                   use_value=use_value, compute_dtype=section.dtype, backend=section.backend)

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
        if self.value_dtype not in _DTYPES:
            raise ValueError(f"value_dtype must be one of {list(_DTYPES)}, got {self.value_dtype!r}")
        for name in ("block_rows", "hidden_chunk", "out_chunk", "value_chunk"):
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
    """The negated objective of eq. 2 for each sequence, from its predicted positions:
    ``sum_{j<K} gamma^j c_j - gamma^K V(s_K | g)``, with ``c_j = -R(s_{j+1}, g)`` the 0/1 step
    cost of being outside the goal's tolerance; without the value term (``use_value=False`` or no
    ``final_values``) that of eq. 1, the finite-horizon objective.

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
# Terminal value network (TD3 actor + twin critic) as plain parameters
# --------------------------------------------------------------------------------------------

@flax.struct.dataclass
class ValueNet:
    """The parameters of V(s, g) = min(Q1, Q2)(s, g, clip(pi(s, g))) (TD3's ``td3_value``).

    Passing one to :func:`mpc_actions` / :func:`sequence_costs` lets the fused kernel evaluate the
    terminal value on the final states while they are still on chip. Build it with
    :func:`td3_value_net`. The actor and both critic heads must be flax MLPs with 2 hidden ReLU
    layers for the fused path (other depths fall back to XLA).
    """

    actor_params: Any
    critic_params: Any
    output_normalisation: bool = flax.struct.field(pytree_node=False, default=False)
    max_action: float = flax.struct.field(pytree_node=False, default=1.0)


def td3_value_net(td3_cfg, td3_state) -> ValueNet:
    """The online actor and twin critic of a TD3 state (``TD3Config``, ``TD3State``) as a ValueNet."""
    return ValueNet(actor_params=td3_state.actor_params, critic_params=td3_state.critic_params,
                    output_normalisation=bool(td3_cfg.output_normalisation),
                    max_action=float(td3_cfg.max_action))


def _mlp_hidden(params) -> tuple:
    n = sum(1 for k in params if k.startswith("hidden_"))
    return tuple(int(params[f"hidden_{i}"]["kernel"].shape[-1]) for i in range(n))


def value_net_fn(net: ValueNet) -> Callable:
    """value_fn(states (..., obs), goal (2,) or (..., 2)) -> (...) computing exactly td3_value (XLA)."""
    actor = Actor(action_dim=actor_action_dim(net.actor_params), hidden=_mlp_hidden(net.actor_params["params"]),
                  output_normalisation=net.output_normalisation, max_action=net.max_action)
    critic = TwinCritic(hidden=_mlp_hidden(net.critic_params["params"]["heads"]))

    def value_fn(states, goal):
        g = jnp.broadcast_to(goal, states[..., :2].shape)
        a = jnp.clip(actor.apply(net.actor_params, states, g), -net.max_action, net.max_action)
        return jnp.min(critic.apply(net.critic_params, states, g, a), axis=0)

    return value_fn


def _fusable(net: Optional[ValueNet], obs_dim: int) -> bool:
    if net is None:
        return False
    ap, cp = net.actor_params["params"], net.critic_params["params"]["heads"]
    return (len(_mlp_hidden(ap)) == 2 and len(_mlp_hidden(cp)) == 2
            and ap["hidden_0"]["kernel"].shape[-2] == obs_dim + 2
            and cp["hidden_0"]["kernel"].shape[-2] == obs_dim + 2 + ap["out"]["kernel"].shape[-1])


# --------------------------------------------------------------------------------------------
# Fused rollout kernel (Pallas, Triton on GPU)
# --------------------------------------------------------------------------------------------

def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def _pad_to(x, shape):
    return jnp.pad(x, [(0, t - s) for s, t in zip(x.shape, shape)])


def _hash_uniform(ctr, seed):
    """Uniform in [-1, 1) from an integer counter and seed (same bits for int32 and uint32 inputs):
    Wellons' triple32 integer hash of ctr * golden + seed, top 24 bits. Runs inside the kernel and in
    XLA (to recover the chosen first action)."""
    dt = ctr.dtype

    def k(v):
        return np.array(v, np.uint32).astype(dt)

    def srl(x, n):
        return jax.lax.shift_right_logical(x, k(n))

    x = ctr * k(0x9E3779B9) + seed
    x = x ^ srl(x, 17)
    x = x * k(0xED5AD4BB)
    x = x ^ srl(x, 11)
    x = x * k(0xAC4C1B51)
    x = x ^ srl(x, 15)
    x = x * k(0x31848BAB)
    x = x ^ srl(x, 14)
    return srl(x, 8).astype(jnp.float32) * np.float32(2.0 / (1 << 24)) - np.float32(1.0)


def _rng_seeds(key, B):
    """One uint32 seed per environment for the in-kernel sampler."""
    return jax.random.bits(key, (B, 1), jnp.uint32)


def _kernel_rng_actions(seeds, K, Mp, AP, act_dim, t=None, rows=None):
    """The actions the kernel draws: (B, K, Mp, AP) bf16 (zero padding lanes), or for given step t
    and rows (B, R) only those, (B, R, act_dim) bf16. seeds (B, 1) uint32."""
    if rows is None:
        ctr = ((jnp.arange(K, dtype=jnp.uint32)[:, None, None] * Mp + jnp.arange(Mp, dtype=jnp.uint32)[:, None]) * AP
               + jnp.arange(AP, dtype=jnp.uint32))[None]  # (1, K, Mp, AP)
        u = _hash_uniform(ctr, seeds[:, :, None, None])
        lane = jnp.arange(AP)
        return jnp.where(lane < act_dim, u, 0.0).astype(jnp.bfloat16)
    ctr = (jnp.uint32(t * Mp) + rows.astype(jnp.uint32)[..., None]) * AP + jnp.arange(act_dim, dtype=jnp.uint32)
    return _hash_uniform(ctr, seeds[:, :, None]).astype(jnp.bfloat16)


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


def _value_width(mpc_cfg: MPCConfig, net: ValueNet) -> int:
    widths = _mlp_hidden(net.actor_params["params"]) + _mlp_hidden(net.critic_params["params"]["heads"])
    VC = mpc_cfg.value_chunk
    return -(-max(widths) // VC) * VC


def _kernel_value_weights(mpc_cfg: MPCConfig, net: ValueNet, goal, obs_dim, SP, AP):
    """Padded value-net operands of the kernel. The goal enters the first layers as a per-env bias
    (computed here in float32), so the kernel multiplies only the state (and action) parts."""
    f32 = jnp.float32
    vdt = _DTYPES[mpc_cfg.value_dtype]
    HV = _value_width(mpc_cfg, net)
    hi = jax.lax.Precision.HIGHEST
    B = goal.shape[0]
    ap, cp = net.actor_params["params"], net.critic_params["params"]["heads"]
    k0 = ap["hidden_0"]["kernel"].astype(f32)
    a_ws = _pad_to(k0[:obs_dim], (SP, HV)).astype(vdt)
    a_g = jnp.dot(goal, k0[obs_dim:obs_dim + 2], precision=hi) + ap["hidden_0"]["bias"]
    a_g = _pad_to(a_g.astype(f32), (B, HV))[:, None, :]
    a_w2 = _pad_to(ap["hidden_1"]["kernel"], (HV, HV)).astype(vdt)
    a_b2 = _pad_to(ap["hidden_1"]["bias"].astype(f32), (HV,))[None, :]
    a_w3 = _pad_to(ap["out"]["kernel"], (HV, AP)).astype(vdt)
    a_b3 = _pad_to(ap["out"]["bias"].astype(f32), (AP,))[None, :]
    c0 = cp["hidden_0"]["kernel"].astype(f32)  # (2, obs + 2 + A, H)
    nh = c0.shape[0]
    c_ws = _pad_to(c0[:, :obs_dim], (nh, SP, HV)).astype(vdt)
    c_wa = _pad_to(c0[:, obs_dim + 2:], (nh, AP, HV)).astype(vdt)
    c_g = jnp.einsum("bd,jdh->bjh", goal, c0[:, obs_dim:obs_dim + 2], precision=hi) + cp["hidden_0"]["bias"][None]
    c_g = _pad_to(c_g.astype(f32), (B, nh, HV))
    c_w2 = _pad_to(cp["hidden_1"]["kernel"], (nh, HV, HV)).astype(vdt)
    c_b2 = _pad_to(cp["hidden_1"]["bias"].astype(f32), (nh, HV))
    c_w3 = _pad_to(cp["out"]["kernel"][..., 0].astype(f32), (nh, HV))
    c_b3 = cp["out"]["bias"][:, 0].astype(f32)  # added outside the kernel
    return (a_ws, a_g, a_w2, a_b2, a_w3, a_b3, c_ws, c_wa, c_g, c_w2, c_b2, c_w3), c_b3, HV


def _rollout_pallas(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, fd: FoldedDynamics, obs, goal, acts_k,
                    interpret: bool = False, value_net: Optional[ValueNet] = None, want_final: bool = True):
    """Fused K-step rollout, optionally with the terminal value of each final state.

    obs (B, obs), goal (B, 2), acts_k (B, K, Mp, AP) bf16 (kernel layout, zero padding lanes), or
    (B, 1) uint32 seeds: the kernel then draws the actions itself (``_kernel_rng_actions``).
    Returns a dict: "cost" (B, Mp) discounted step-cost sums; "final" (B, Mp, SP) float32 final
    states (if want_final); with value_net also "value" (B, Mp) = min(Q1, Q2)(s_K, g, pi(s_K, g)) and
    "at_goal" (B, Mp) (bool) from the final states, computed inside the kernel.
    """

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
    draw = acts_k.dtype == jnp.uint32
    if draw:
        if acts_k.shape != (B, 1):
            raise ValueError(f"kernel seeds must be {(B, 1)}, got {acts_k.shape}")
        if K * Mp * AP >= 2 ** 31:
            raise ValueError("too many samples for the in-kernel sampler's 31-bit counter")
        acts_k = jax.lax.bitcast_convert_type(acts_k, jnp.int32)
    elif acts_k.shape != (B, K, Mp, AP):
        raise ValueError(f"kernel actions must be {(B, K, Mp, AP)}, got {acts_k.shape}")

    ws, wa, b1, w2, b2, w3, b3 = _kernel_weights(fd, SP, AP, HP)
    join_wanted = B >= _JOIN_MIN_ENVS if mpc_cfg.join_input is None else mpc_cfg.join_input
    join = join_wanted and AP <= SP
    if join and not draw:  # explicit actions: widen to the state's lanes for the interleaved operand
        acts_k = _pad_to(acts_k, (B, K, Mp, SP))
    if join:  # rows 2j: state input j, rows 2j + 1: action input j (zero past the action size)
        wa32 = _pad_to(wa, (E, SP, HP))
        ws = jnp.stack([ws, wa32], axis=2).reshape(E, 2 * SP, HP)
    s0 = _pad_to(obs.astype(f32), (B, SP))
    g = _pad_to(goal.astype(f32), (B, SP))

    fused = value_net is not None
    if fused:
        if not _fusable(value_net, obs_dim):
            raise ValueError("the fused value needs an actor and twin critic with 2 hidden layers on (obs, goal xy)")
        vweights, c_b3, HV = _kernel_value_weights(mpc_cfg, value_net, goal.astype(f32), obs_dim, SP, AP)
        v_act_dim = int(value_net.actor_params["params"]["out"]["kernel"].shape[-1])
        if v_act_dim != act_dim:
            raise ValueError(f"actor action size {v_act_dim} != dynamics action size {act_dim}")
        vdt = _DTYPES[mpc_cfg.value_dtype]
        VC = mpc_cfg.value_chunk
        nV = HV // VC
        n_heads = vweights[6].shape[0]
        max_a = float(value_net.max_action)
        norm_out = bool(value_net.output_normalisation)
    else:
        vweights = ()

    def leaky(x):
        return jnp.maximum(x, slope * x)

    def relu(x):
        return jnp.maximum(x, 0.0)

    mean_mode = mpc_cfg.ensemble_mode == "mean" and E > 1
    if mean_mode:  # every program loops over all members: the output layer's bias is averaged once
        b3 = jnp.broadcast_to(b3.mean(0, keepdims=True), b3.shape)

    def value_terms(s, refs):
        """min-less twin Q of the final states s (BM, SP): returns the heads' Q without output bias."""
        a_ws, a_g, a_w2, a_b2, a_w3, a_b3, c_ws, c_wa, c_g, c_w2, c_b2, c_w3 = refs
        sv = s.astype(vdt)

        def layer2(h1, w2_at, b2_at, c):  # hidden block c of the second layer, from the first-layer blocks
            c0 = pl.multiple_of(c * VC, VC)
            acc = jnp.dot(h1[0], w2_at(pl.ds(0, VC), pl.ds(c0, VC)), preferred_element_type=f32)
            for k in range(1, nV):
                acc = acc + jnp.dot(h1[k], w2_at(pl.ds(k * VC, VC), pl.ds(c0, VC)), preferred_element_type=f32)
            return relu(acc + b2_at(pl.ds(c0, VC))), c0

        # actor pi(s, g)
        h1 = [relu(jnp.dot(sv, a_ws[:, pl.ds(k * VC, VC)], preferred_element_type=f32)
                   + a_g[:, pl.ds(k * VC, VC)]).astype(vdt) for k in range(nV)]

        def actor_block(c, acc):
            h2, c0 = layer2(h1, lambda r, q: a_w2[r, q], lambda q: a_b2[:, q], c)
            return acc + jnp.dot(h2.astype(vdt), a_w3[pl.ds(c0, VC), :], preferred_element_type=f32)

        araw = jax.lax.fori_loop(0, nV, actor_block, jnp.zeros((BM, AP), f32)) + a_b3[...]
        if norm_out:  # padding lanes of araw are exactly 0
            scale = jnp.maximum(1.0, jnp.sum(jnp.abs(araw), axis=1) * (1.0 / act_dim))
            act = araw / scale[:, None]
        else:
            act = max_a * jnp.tanh(araw)
        act = jnp.minimum(jnp.maximum(act, -max_a), max_a).astype(vdt)

        qs = []
        for j in range(n_heads):
            h1 = [relu(jnp.dot(sv, c_ws[j, :, pl.ds(k * VC, VC)], preferred_element_type=f32)
                       + jnp.dot(act, c_wa[j, :, pl.ds(k * VC, VC)], preferred_element_type=f32)
                       + c_g[pl.ds(j, 1), pl.ds(k * VC, VC)]).astype(vdt) for k in range(nV)]

            def critic_block(c, acc, j=j, h1=h1):
                h2, c0 = layer2(h1, lambda r, q: c_w2[j, r, q], lambda q: c_b2[pl.ds(j, 1), q], c)
                return acc + jnp.sum(h2 * c_w3[pl.ds(j, 1), pl.ds(c0, VC)], axis=1)

            qs.append(jax.lax.fori_loop(0, nV, critic_block, jnp.zeros((BM,), f32)))
        return qs

    def kernel(s0_ref, g_ref, a_ref, ws_ref, wa_ref, b1_ref, w2_ref, b2_ref, w3_ref, b3_ref, *rest):
        vrefs, outs = rest[:len(vweights)], list(rest[len(vweights):])
        cost_ref = outs.pop(0)
        sk_ref = outs.pop(0) if want_final else None
        s = jnp.broadcast_to(s0_ref[...], (BM, SP))
        gg = g_ref[...]
        lane = jax.lax.broadcasted_iota(jnp.int32, (1, SP), 1)
        xy_lane = lane < 2
        if draw:  # counters of this block's rows and action lanes at step 0
            AW = SP if join else AP  # lanes of the drawn tile (the counter keeps AP lanes per row)
            a_lane = jax.lax.broadcasted_iota(jnp.int32, (BM, AW), 1)
            a_row = jax.lax.broadcasted_iota(jnp.int32, (BM, AW), 0) + pl.program_id(1) * BM
            seed = jnp.broadcast_to(a_ref[...], (BM, AW))

        def actions(t):
            if not draw:
                return a_ref[t]  # (BM, AP) bf16, or (BM, SP) with join
            u = _hash_uniform((t * Mp + a_row) * AP + a_lane, seed)
            return jnp.where(a_lane < act_dim, u, 0.0).astype(bf)

        def W(ref, e, *idx):  # a weight tile of member e (member mode: the block is one member)
            return ref[(e,) + idx] if mean_mode else ref[idx]

        def member_delta(e, sb, a):
            h1 = []
            x = jnp.stack([sb, a], axis=-1).reshape(BM, 2 * SP) if join else None
            for k in range(nH):
                if join:
                    acc = jnp.dot(x, W(ws_ref, e, slice(None), pl.ds(k * CH, CH)), preferred_element_type=f32)
                else:
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

        def dist2(s):
            return jnp.sum(jnp.where(xy_lane, jnp.square(s - gg), 0.0), axis=1)

        def step(t, carry):
            s, cost, disc = carry
            a = actions(t)
            sb = s.astype(bf)
            if mean_mode:
                ds = jax.lax.fori_loop(0, E, lambda e, acc: acc + member_delta(e, sb, a),
                                       jnp.zeros((BM, SP), f32)) * (1.0 / E)
                s = s + ds + W(b3_ref, 0, slice(None), slice(None))
            else:
                s = s + member_delta(0, sb, a) + b3_ref[...]
            cost = cost + disc * (dist2(s) > tol2).astype(f32)
            return s, cost, disc * gamma

        s, cost, _ = jax.lax.fori_loop(0, K, step, (s, jnp.zeros((BM,), f32), jnp.float32(1.0)))
        cost_ref[...] = cost[None, :]
        if want_final:
            sk_ref[...] = s
        if fused:
            at_goal_ref = outs.pop(0)
            at_goal_ref[...] = (dist2(s) <= tol2).astype(f32)[None, :]
            for q_ref, q in zip(outs, value_terms(s, vrefs)):
                q_ref[...] = q[None, :]

    nb = Mp // BM
    def wspec(shape):
        if mean_mode:  # all members in every program
            return pl.BlockSpec((E,) + shape, lambda b, i: (0, 0, 0))
        return pl.BlockSpec((None,) + shape, lambda b, i: (i % E, 0, 0))

    def full(x):
        return pl.BlockSpec(x.shape, lambda b, i, n=x.ndim: (0,) * n)

    def per_env(x):  # (B, ...) -> this env's slice
        return pl.BlockSpec((None,) + x.shape[1:], lambda b, i, n=x.ndim: (b,) + (0,) * (n - 1))

    in_specs = [
        pl.BlockSpec((1, SP), lambda b, i: (b, 0)),
        pl.BlockSpec((1, SP), lambda b, i: (b, 0)),
        (pl.BlockSpec((1, 1), lambda b, i: (b, 0)) if draw else
         pl.BlockSpec((None, K, BM, SP if join else AP), lambda b, i: (b, 0, i, 0))),
        wspec(((2 if join else 1) * SP, HP)), wspec((AP, HP)), wspec((1, HP)), wspec((HP, HP)), wspec((1, HP)),
        wspec((HP, SP)), wspec((1, SP)),
    ]
    row_spec = pl.BlockSpec((1, BM), lambda b, i: (b, i))
    out_specs = [row_spec]
    out_shape = [jax.ShapeDtypeStruct((B, Mp), f32)]
    if want_final:
        out_specs.append(pl.BlockSpec((None, BM, SP), lambda b, i: (b, i, 0)))
        out_shape.append(jax.ShapeDtypeStruct((B, Mp, SP), f32))
    flops = 2 * B * Mp * K * ((2 * SP if join else SP + AP) * HP + HP * HP + HP * SP) * (E if mean_mode else 1)
    if fused:
        for k, x in enumerate(vweights):
            in_specs.append(per_env(x) if k in (1, 8) else full(x))
        for _ in range(1 + n_heads):
            out_specs.append(row_spec)
            out_shape.append(jax.ShapeDtypeStruct((B, Mp), f32))
        flops += 2 * B * Mp * ((SP + AP) * HV + HV * HV + n_heads * (SP * HV + AP * HV + HV * HV + HV))
    kwargs = {}
    if not interpret:
        kwargs["compiler_params"] = plgpu.CompilerParams(num_warps=mpc_cfg.num_warps,
                                                         num_stages=mpc_cfg.num_stages)
    outs = pl.pallas_call(
        kernel,
        grid=(B, nb),
        in_specs=in_specs,
        out_specs=out_specs,
        out_shape=out_shape,
        interpret=interpret,
        cost_estimate=pl.CostEstimate(flops=int(flops), transcendentals=0,
                                      bytes_accessed=int(B * Mp * ((0 if draw else K * AP * 2) + (SP * 4 if want_final else 0) + 16))),
        name="mpc_rollout",
        **kwargs,
    )(s0, g, acts_k, ws, wa, b1, w2, b2, w3, b3, *vweights)
    outs = list(outs)
    res = {"cost": outs.pop(0)}
    if want_final:
        res["final"] = outs.pop(0)
    if fused:
        res["at_goal"] = outs.pop(0) > 0.5
        qs = jnp.stack(outs) + c_b3[:, None, None]  # (heads, B, Mp)
        res["value"] = jnp.min(qs, axis=0)
    return res


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


def _check_value_args(mpc_cfg, value_fn, value_net):
    if mpc_cfg.use_value and value_fn is None and value_net is None:
        raise ValueError("use_value=True needs a value_fn(states, goal) or a value_net (td3_value_net); "
                         "pass one or set use_value=False")


def _value_callable(value_fn, value_net):
    return value_fn if value_fn is not None else value_net_fn(value_net)


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


def _xla_sequence_costs(mpc_cfg, dyn_cfg, dyn_state, obs, goal, actions, value_fn, value_net):
    """The XLA back end of `sequence_costs`: rollout, terminal values, eq. 2 cost (B, M)."""
    fd = dynamics_fold(dyn_cfg, dyn_state)
    xy, final = _rollout_xla(mpc_cfg, dyn_cfg, fd, obs, actions)
    v = (_values(_value_callable(value_fn, value_net), final, goal, mpc_cfg.value_precision)
         if mpc_cfg.use_value else None)
    return mpc_cost(mpc_cfg, xy, goal, v)


def sequence_costs(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, obs, goal, actions,
                   value_fn: Optional[Callable] = None, interpret: bool = False,
                   value_net: Optional[ValueNet] = None):
    """Eq. 2 cost (B, M) of given sequences actions (B, M, K, A) from obs (B, obs) towards goal (B, 2).

    The terminal value comes from value_fn, or from value_net (see :func:`mpc_actions`)."""
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    actions = jnp.asarray(actions, jnp.float32)
    _check_value_args(mpc_cfg, value_fn, value_net)
    backend = _resolve_backend(mpc_cfg, dyn_cfg) if not interpret else "pallas"
    B, M = actions.shape[:2]
    if backend == "xla":
        return _xla_sequence_costs(mpc_cfg, dyn_cfg, dyn_state, obs, goal, actions, value_fn, value_net)
    _check_pallas(mpc_cfg, dyn_cfg)
    fd = dynamics_fold(dyn_cfg, dyn_state, jnp.bfloat16)
    SP, AP, HP, BM, Mp = _kernel_dims(mpc_cfg, obs.shape[-1], actions.shape[-1], fd.w_s.shape[2])
    acts_k = _to_kernel_layout(mpc_cfg, actions, AP, Mp)
    return _finish_pallas(mpc_cfg, fd, obs, goal, acts_k, value_fn, value_net, M, dyn_cfg, interpret)


def _finish_pallas(mpc_cfg, fd, obs, goal, acts_k, value_fn, value_net, M, dyn_cfg, interpret=False):
    """Eq. 2 costs (B, M) from the kernel: the value fused into it when value_net allows, else XLA."""
    obs_dim = obs.shape[-1]
    if not mpc_cfg.use_value:
        return _rollout_pallas(mpc_cfg, dyn_cfg, fd, obs, goal, acts_k, interpret, want_final=False)["cost"][:, :M]
    if mpc_cfg.fuse_value and _fusable(value_net, obs_dim):
        r = _rollout_pallas(mpc_cfg, dyn_cfg, fd, obs, goal, acts_k, interpret, value_net=value_net,
                            want_final=False)
        return _terminal(mpc_cfg, r["cost"][:, :M], r["at_goal"][:, :M], r["value"][:, :M])
    r = _rollout_pallas(mpc_cfg, dyn_cfg, fd, obs, goal, acts_k, interpret)
    final = r["final"][:, :M, :obs_dim]
    v = _values(_value_callable(value_fn, value_net), final, goal, mpc_cfg.value_precision)
    at_goal = jnp.sum(jnp.square(final[..., :2] - goal[:, None, :]), -1) <= jnp.float32(mpc_cfg.goal_tolerance) ** 2
    return _terminal(mpc_cfg, r["cost"][:, :M], at_goal, v)


def mpc_actions(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, key, obs, goal,
                value_fn: Optional[Callable] = None, return_info: bool = False,
                value_net: Optional[ValueNet] = None):
    """MPC decisions for a batch of environments: obs (B, obs), goal (B, 2) -> actions (B, A).

    One key draws all environments' sequences. The terminal value (required when use_value=True)
    comes from either
    - value_fn(states (M, obs), goal (2,)) -> (M,), any callable, vmapped over environments, or
    - value_net, the TD3 actor and critic parameters (:func:`td3_value_net`). With the fused
      kernel (backend "pallas", ``fuse_value=True``) V is computed inside the kernel on the final
      states (``value_dtype`` operands, float32 accumulation); on the XLA path it is td3_value.
    When both are given, the fused kernel uses value_net and every other path uses value_fn, so
    they must compute the same V. With return_info, also returns a dict with the chosen sequence's
    cost ("cost", (B,)) and index ("index", (B,)).
    """
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    if obs.ndim != 2 or goal.shape != (obs.shape[0], 2):
        raise ValueError(f"obs must be (B, obs_dim) and goal (B, 2), got {obs.shape} and {goal.shape}")
    _check_value_args(mpc_cfg, value_fn, value_net)
    act_dim = dyn_state.norm.act_mean.shape[0]
    B, M, K = obs.shape[0], mpc_cfg.num_samples, mpc_cfg.horizon
    backend = _resolve_backend(mpc_cfg, dyn_cfg)
    if backend == "xla":
        actions = sample_action_sequences(key, mpc_cfg, B, act_dim)
        cost = _xla_sequence_costs(mpc_cfg, dyn_cfg, dyn_state, obs, goal, actions, value_fn, value_net)
        first = actions[:, :, 0, :]
    else:
        _check_pallas(mpc_cfg, dyn_cfg)
        interpret = jax.default_backend() != "gpu"   # off a GPU the kernel can only be interpreted
        fd = dynamics_fold(dyn_cfg, dyn_state, jnp.bfloat16)
        SP, AP, HP, BM, Mp = _kernel_dims(mpc_cfg, obs.shape[-1], act_dim, fd.w_s.shape[2])
        if mpc_cfg.kernel_rng:  # the kernel draws the sequences; recover the chosen first actions
            seeds = _rng_seeds(key, B)
            cost = _finish_pallas(mpc_cfg, fd, obs, goal, seeds, value_fn, value_net, M, dyn_cfg,
                                  interpret)
            first = lambda idx: _kernel_rng_actions(seeds, K, Mp, AP, act_dim, t=0, rows=idx)
        else:  # draw directly in the kernel layout (rows past M are never chosen)
            a = jax.random.uniform(key, (B, K, Mp, act_dim), jnp.float32, -1.0, 1.0).astype(jnp.bfloat16)
            cost = _finish_pallas(mpc_cfg, fd, obs, goal, _pad_to(a, (B, K, Mp, AP)), value_fn, value_net, M,
                                  dyn_cfg, interpret)
            first = a[:, 0, :M, :]
    idx = jnp.argmin(cost, axis=-1)
    if callable(first):
        best = first(idx[:, None])[:, 0, :].astype(jnp.float32)
    else:
        best = jnp.take_along_axis(first, idx[:, None, None], axis=1)[:, 0, :].astype(jnp.float32)
    if return_info:
        return best, {"cost": jnp.take_along_axis(cost, idx[:, None], 1)[:, 0], "index": idx}
    return best


def mpc_action(mpc_cfg: MPCConfig, dyn_cfg: DynamicsConfig, dyn_state: DynamicsState, key, obs, goal,
               value_fn: Optional[Callable] = None, value_net: Optional[ValueNet] = None):
    """One environment's MPC decision: obs (obs_dim,), goal (2,) -> action (A,).

    Same as ``mpc_actions`` on a batch of one with the same key."""
    obs = jnp.asarray(obs, jnp.float32)
    goal = jnp.asarray(goal, jnp.float32)
    if obs.ndim != 1 or goal.shape != (2,):
        raise ValueError(f"obs must be (obs_dim,) and goal (2,), got {obs.shape} and {goal.shape}")
    return mpc_actions(mpc_cfg, dyn_cfg, dyn_state, key, obs[None], goal[None], value_fn, value_net=value_net)[0]


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

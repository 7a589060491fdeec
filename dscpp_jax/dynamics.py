"""Learned dynamics: an ensemble of MLPs that predict the standardised state change.

Paper appendix 4.1 (after Nagabandi et al. 2018): f(s, a) is a 2 x 500 LeakyReLU MLP on standardised
(s, a) that predicts the standardised change in state, so

    s' = s + out * sigma_delta + mu_delta.

Adam 1e-3, batch 1024. The paper uses one model (``ensemble_size=1``); members beyond the first are
vmapped copies with their own initialisation and their own bootstrap minibatches. The normalisation
statistics live in :class:`DynamicsState` and are refreshed with :func:`dynamics_fit_normaliser` from a
masked buffer before a training pass, as the original recomputed them from its replay before training.

Everything here is a pure function of typed pytrees; ``DynamicsConfig`` is static (hashable).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from dscpp_jax.config import DynamicsSection
from dscpp_jax.replay import valid_positions

__all__ = [
    "DynamicsConfig",
    "DynamicsMLP",
    "Normaliser",
    "DynamicsState",
    "FoldedDynamics",
    "dynamics_init",
    "dynamics_fit_normaliser",
    "dynamics_loss",
    "dynamics_update",
    "dynamics_train",
    "dynamics_predict",
    "dynamics_predict_all",
    "dynamics_metrics",
    "dynamics_fold",
    "folded_step",
]


@dataclasses.dataclass(frozen=True)
class DynamicsConfig:
    """Static settings of the dynamics ensemble.

    ensemble_size: number of members E (1 = the paper's single model).
    hidden: hidden layer widths (paper: 500, 500).
    lr: Adam learning rate (paper: 1e-3).
    batch_size: minibatch size per member and step (paper: 1024).
    negative_slope: LeakyReLU slope (PyTorch default 0.01, as the original).
    min_std: floor for a standard deviation (the original replaced exact zeros by 1e-5).
    """

    ensemble_size: int = 1
    hidden: tuple[int, ...] = (500, 500)
    lr: float = 1e-3
    batch_size: int = 1024
    negative_slope: float = 0.01
    min_std: float = 1e-5

    def __post_init__(self):
        if self.ensemble_size < 1:
            raise ValueError(f"ensemble_size must be >= 1, got {self.ensemble_size}")
        if len(self.hidden) < 1 or any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"hidden must be a non-empty tuple of positive widths, got {self.hidden}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))

    @classmethod
    def from_section(cls, section: DynamicsSection) -> "DynamicsConfig":
        """The dynamics model f_xi a run config's `dynamics` section sets."""
        return cls(ensemble_size=section.ensemble, hidden=(section.hidden, section.hidden),
                   lr=section.lr, batch_size=section.batch_size)


class DynamicsMLP(nn.Module):
    """(standardised s ⊕ a) -> hidden LeakyReLU layers -> standardised state change."""

    obs_dim: int
    hidden: Sequence[int] = (500, 500)
    negative_slope: float = 0.01

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = nn.leaky_relu(nn.Dense(h)(x), self.negative_slope)
        return nn.Dense(self.obs_dim)(x)


@struct.dataclass
class Normaliser:
    """Standardisation statistics (population mean and std over the valid buffer entries)."""

    obs_mean: jax.Array
    obs_std: jax.Array
    act_mean: jax.Array
    act_std: jax.Array
    delta_mean: jax.Array
    delta_std: jax.Array


@struct.dataclass
class DynamicsState:
    """Ensemble parameters (leading axis E), Adam state, normaliser and step counter."""

    params: Any
    opt_state: Any
    norm: Normaliser
    step: jax.Array


@struct.dataclass
class FoldedDynamics:
    """The ensemble with the normalisation folded into the weights, for fast rollouts.

    Per member e: h = leaky(s @ w_s[e] + a @ w_a[e] + b[0][e]); h = leaky(h @ w[i][e] + b[i][e]) for
    the middle layers; s' = s + h @ w_out[e] + b_out[e]. Mathematically identical to
    :func:`dynamics_predict` with the same member.
    """

    w_s: jax.Array  # (E, obs_dim, H0)
    w_a: jax.Array  # (E, act_dim, H0)
    b_in: jax.Array  # (E, H0)
    w_hidden: tuple  # ((E, H_i, H_{i+1}), ...)
    b_hidden: tuple  # ((E, H_{i+1}), ...)
    w_out: jax.Array  # (E, H_last, obs_dim)
    b_out: jax.Array  # (E, obs_dim)


def _module(cfg: DynamicsConfig, obs_dim: int) -> DynamicsMLP:
    return DynamicsMLP(obs_dim=obs_dim, hidden=cfg.hidden, negative_slope=cfg.negative_slope)


def _optimizer(cfg: DynamicsConfig):
    return optax.adam(cfg.lr)


def _obs_dim(state: DynamicsState) -> int:
    return state.norm.obs_mean.shape[-1]


def dynamics_init(key, obs_dim: int, action_dim: int, cfg: DynamicsConfig = DynamicsConfig()) -> DynamicsState:
    """Fresh ensemble (E independent initialisations) with identity normalisation statistics."""
    if obs_dim < 1 or action_dim < 1:
        raise ValueError(f"obs_dim and action_dim must be positive, got {obs_dim}, {action_dim}")
    module = _module(cfg, obs_dim)
    x = jnp.zeros((1, obs_dim + action_dim), jnp.float32)
    keys = jax.random.split(key, cfg.ensemble_size)
    params = jax.vmap(lambda k: module.init(k, x))(keys)
    norm = Normaliser(
        obs_mean=jnp.zeros((obs_dim,), jnp.float32),
        obs_std=jnp.ones((obs_dim,), jnp.float32),
        act_mean=jnp.zeros((action_dim,), jnp.float32),
        act_std=jnp.ones((action_dim,), jnp.float32),
        delta_mean=jnp.zeros((obs_dim,), jnp.float32),
        delta_std=jnp.ones((obs_dim,), jnp.float32),
    )
    return DynamicsState(params=params, opt_state=_optimizer(cfg).init(params), norm=norm,
                         step=jnp.zeros((), jnp.int32))


def _flatten_rows(x, trailing: int):
    x = jnp.asarray(x)
    return x.reshape((-1,) + x.shape[x.ndim - trailing:]) if trailing else x.reshape(-1)


def _masked_mean_std(x, w, min_std):
    n = jnp.maximum(w.sum(), 1.0)
    x = jnp.where(w[:, None] > 0, x, 0.0)  # invalid rows may hold anything (even NaN)
    mean = (x * w[:, None]).sum(0) / n
    var = (jnp.square(x - mean) * w[:, None]).sum(0) / n
    std = jnp.sqrt(var)
    return mean, jnp.maximum(std, min_std)


def dynamics_fit_normaliser(state: DynamicsState, obs, act, next_obs, mask=None,
                            cfg: DynamicsConfig = DynamicsConfig()) -> DynamicsState:
    """Recompute the standardisation statistics from the valid rows of a buffer.

    obs/next_obs (..., obs_dim), act (..., act_dim), mask (...) bool/0-1 (None = all valid). Leading
    axes are flattened (so a time-major replay works as is). With no valid row the stats are unchanged.
    """
    obs_dim = _obs_dim(state)
    obs = _flatten_rows(obs, 1).astype(jnp.float32)
    next_obs = _flatten_rows(next_obs, 1).astype(jnp.float32)
    act = _flatten_rows(act, 1).astype(jnp.float32)
    if obs.shape[-1] != obs_dim or next_obs.shape != obs.shape or act.shape[0] != obs.shape[0]:
        raise ValueError(f"obs {obs.shape}, act {act.shape}, next_obs {next_obs.shape} do not match "
                         f"obs_dim={obs_dim}")
    w = jnp.ones(obs.shape[:1], jnp.float32) if mask is None else _flatten_rows(mask, 0).astype(jnp.float32)
    if w.shape[0] != obs.shape[0]:
        raise ValueError(f"mask has {w.shape[0]} rows, buffer has {obs.shape[0]}")
    om, os_ = _masked_mean_std(obs, w, cfg.min_std)
    am, as_ = _masked_mean_std(act, w, cfg.min_std)
    dm, ds = _masked_mean_std(next_obs - obs, w, cfg.min_std)
    new = Normaliser(om, os_, am, as_, dm, ds)
    any_valid = w.sum() > 0
    new = jax.tree.map(lambda a, b: jnp.where(any_valid, a, b), new, state.norm)
    return state.replace(norm=new)


def _standardise_inputs(norm: Normaliser, obs, act):
    return jnp.concatenate([(obs - norm.obs_mean) / norm.obs_std, (act - norm.act_mean) / norm.act_std], -1)


def _apply_member(cfg, obs_dim, params, x):
    return _module(cfg, obs_dim).apply(params, x)


def dynamics_loss(cfg: DynamicsConfig, params, norm: Normaliser, obs, act, next_obs, weight=None):
    """The dynamics model's loss (one member's params): the mean squared error between the
    member's output and the standardised state change, the model ``s_{t+1} = s_t + f_xi(s_t, a_t)``
    of Nagabandi et al. 2018 that the paper learns for MPC (eq. 1 and 2; appendix, "Deep
    Model-based RL"). ``weight`` (B,): optional per-row weights (a weighted mean)."""
    obs_dim = obs.shape[-1]
    x = _standardise_inputs(norm, obs, act)
    target = ((next_obs - obs) - norm.delta_mean) / norm.delta_std
    err = jnp.square(_apply_member(cfg, obs_dim, params, x) - target).mean(-1)
    if weight is None:
        return err.mean()
    return (err * weight).sum() / jnp.maximum(weight.sum(), 1.0)


def dynamics_update(cfg: DynamicsConfig, state: DynamicsState, batch, key):
    """One Adam step of every member.

    batch = (obs, act, next_obs) with shapes (B, d) (each member draws its own bootstrap resample of
    the B rows; with E = 1 the batch is used as is) or (E, B, d) (member e trains on batch[e]).
    Returns (state, metrics) with metrics["loss"] the mean standardised MSE over members.
    """
    obs, act, next_obs = (jnp.asarray(b, jnp.float32) for b in batch)
    E = cfg.ensemble_size
    if obs.ndim == 2:
        if E == 1:
            obs, act, next_obs = obs[None], act[None], next_obs[None]
        else:
            B = obs.shape[0]
            idx = jax.random.randint(key, (E, B), 0, B)
            obs, act, next_obs = obs[idx], act[idx], next_obs[idx]
    if obs.ndim != 3 or obs.shape[0] != E:
        raise ValueError(f"batch obs must be (B, d) or (E={E}, B, d), got {obs.shape}")

    def loss_fn(p):
        losses = jax.vmap(lambda pe, o, a, n: dynamics_loss(cfg, pe, state.norm, o, a, n))(p, obs, act, next_obs)
        return losses.sum(), losses

    (_, losses), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
    updates, opt_state = _optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    new = state.replace(params=params, opt_state=opt_state, step=state.step + 1)
    return new, {"loss": losses.mean(), "loss_per_member": losses}


def _buffer_arrays(buffer):
    """(obs, act, next_obs, mask) from a tuple or from an object with obs/action/next_obs/valid."""
    if isinstance(buffer, (tuple, list)):
        if len(buffer) == 3:
            obs, act, nxt = buffer
            mask = None
        elif len(buffer) == 4:
            obs, act, nxt, mask = buffer
        else:
            raise ValueError("buffer tuple must be (obs, act, next_obs[, mask])")
    else:  # a replay ring (``data`` pytree + ``valid``) or any object with the three fields
        data = getattr(buffer, "data", buffer)
        get = (lambda k: data[k]) if isinstance(data, dict) else (lambda k: getattr(data, k))
        try:
            obs, act, nxt = get("obs"), get("action"), get("next_obs")
        except (KeyError, AttributeError) as e:
            raise ValueError("buffer must be (obs, act, next_obs[, mask]) or hold obs/action/next_obs "
                             f"fields (directly or in .data): {e}") from None
        mask = getattr(buffer, "valid", None)
    obs = _flatten_rows(obs, 1)
    act = _flatten_rows(act, 1)
    nxt = _flatten_rows(nxt, 1)
    mask = jnp.ones(obs.shape[:1], bool) if mask is None else _flatten_rows(mask, 0)
    return obs, act, nxt, mask


def dynamics_train(cfg: DynamicsConfig, state: DynamicsState, buffer, key, num_steps: int):
    """``num_steps`` Adam steps as one ``lax.scan``; each member samples its own minibatch.

    buffer: (obs, act, next_obs[, mask]) arrays with any leading axes, or a replay ring whose ``data``
    holds ``obs``/``action``/``next_obs`` (dict or fields) with its ``valid`` mask. Minibatches are drawn uniformly with replacement
    from the valid rows (fixed shapes: the valid rows' positions are listed once, then each draw is
    a lookup). Normalisation statistics are NOT
    refreshed here: call :func:`dynamics_fit_normaliser` first. Returns (state, metrics) where metrics
    holds the per-step mean loss (num_steps,).
    """
    obs, act, nxt, mask = _buffer_arrays(buffer)
    E, B = cfg.ensemble_size, cfg.batch_size
    positions, total = valid_positions(mask)   # the search of every draw, done once

    def body(st, k):
        u = jax.random.randint(k, (E, B), 0, jnp.maximum(total, 1))
        idx = positions[u]
        b = (obs[idx], act[idx], nxt[idx])
        new, m = dynamics_update(cfg, st, b, k)
        new = jax.tree.map(lambda a, c: jnp.where(total > 0, a, c), new, st)
        return new, m["loss"]

    state, losses = jax.lax.scan(body, state, jax.random.split(key, num_steps))
    return state, {"loss": losses}


def dynamics_predict_all(cfg: DynamicsConfig, state: DynamicsState, obs, action):
    """Next-state predictions of every member: (E, ..., obs_dim)."""
    obs = jnp.asarray(obs, jnp.float32)
    action = jnp.asarray(action, jnp.float32)
    n = state.norm
    x = _standardise_inputs(n, obs, action)
    out = jax.vmap(lambda p: _apply_member(cfg, obs.shape[-1], p, x))(state.params)
    return obs + out * n.delta_std + n.delta_mean


def dynamics_predict(cfg: DynamicsConfig, state: DynamicsState, obs, action, member=None):
    """Predicted next state (..., obs_dim).

    member=None: ensemble mean (for E = 1 the single model); an int: that member; an int array of the
    batch shape (...): a member per row.
    """
    preds = dynamics_predict_all(cfg, state, obs, action)
    if member is None:
        return preds.mean(0)
    member = jnp.asarray(member, jnp.int32)
    if member.ndim == 0:
        return preds[member]
    onehot = jax.nn.one_hot(member, cfg.ensemble_size, dtype=preds.dtype)  # (..., E)
    return jnp.einsum("e...d,...e->...d", preds, onehot)


def dynamics_metrics(cfg: DynamicsConfig, state: DynamicsState, obs, action, next_obs, mask=None):
    """One-step error metrics of the ensemble-mean prediction over the valid rows.

    mse_std: MSE in standardised-delta units (the training loss scale); rmse: root mean squared error
    in raw state units; xy_err: mean Euclidean error of the predicted xy (obs[..., :2]);
    rel_err: ||pred delta - true delta|| / ||true delta|| over all rows (relative error of the change).
    """
    obs, action, next_obs, mask = _buffer_arrays((obs, action, next_obs, mask))
    w = mask.astype(jnp.float32)
    n = jnp.maximum(w.sum(), 1.0)
    pred = dynamics_predict(cfg, state, obs, action)
    err = pred - next_obs
    norm = state.norm
    err_std = err / norm.delta_std
    mse_std = (jnp.square(err_std).mean(-1) * w).sum() / n
    rmse = jnp.sqrt((jnp.square(err).mean(-1) * w).sum() / n)
    xy = (jnp.linalg.norm(err[:, :2], axis=-1) * w).sum() / n
    true_d = (next_obs - obs) * w[:, None]
    rel = jnp.linalg.norm(err * w[:, None]) / jnp.maximum(jnp.linalg.norm(true_d), 1e-12)
    return {"mse_std": mse_std, "rmse": rmse, "xy_err": xy, "rel_err": rel}


def dynamics_fold(cfg: DynamicsConfig, state: DynamicsState, dtype=jnp.float32) -> FoldedDynamics:
    """Fold the input standardisation and output de-standardisation into the weights.

    Weights are cast to ``dtype`` (e.g. bf16 for fast rollouts); biases stay float32.
    """
    n = state.norm
    obs_dim = n.obs_mean.shape[0]
    layers = [state.params["params"][f"Dense_{i}"] for i in range(len(cfg.hidden) + 1)]
    k0, b0 = layers[0]["kernel"], layers[0]["bias"]  # (E, obs+act, H0), (E, H0)
    ks, ka = k0[:, :obs_dim], k0[:, obs_dim:]
    w_s = ks / n.obs_std[None, :, None]
    w_a = ka / n.act_std[None, :, None]
    b_in = b0 - jnp.einsum("d,edh->eh", n.obs_mean / n.obs_std, ks) - jnp.einsum("d,edh->eh", n.act_mean / n.act_std, ka)
    w_hidden = tuple(l["kernel"].astype(dtype) for l in layers[1:-1])
    b_hidden = tuple(l["bias"].astype(jnp.float32) for l in layers[1:-1])
    kl, bl = layers[-1]["kernel"], layers[-1]["bias"]
    w_out = kl * n.delta_std[None, None, :]
    b_out = bl * n.delta_std[None, :] + n.delta_mean[None, :]
    return FoldedDynamics(w_s=w_s.astype(dtype), w_a=w_a.astype(dtype), b_in=b_in.astype(jnp.float32),
                          w_hidden=w_hidden, b_hidden=b_hidden, w_out=w_out.astype(dtype),
                          b_out=b_out.astype(jnp.float32))


def folded_step(fd: FoldedDynamics, obs, action, member=0, negative_slope: float = 0.01,
                compute_dtype=jnp.float32, precision=None):
    """One predicted step with the folded weights of one member (``member`` a static int or traced
    scalar). Matmuls take ``compute_dtype`` operands and accumulate in float32; the state stays
    float32. Returns (..., obs_dim)."""
    def mm(x, w):
        return jnp.dot(x.astype(compute_dtype), w.astype(compute_dtype), preferred_element_type=jnp.float32,
                       precision=precision)

    take = lambda a: a[member]
    h = mm(obs, take(fd.w_s)) + mm(action, take(fd.w_a)) + take(fd.b_in)
    h = jax.nn.leaky_relu(h, negative_slope)
    for w, b in zip(fd.w_hidden, fd.b_hidden):
        h = jax.nn.leaky_relu(mm(h, take(w)) + take(b), negative_slope)
    return obs.astype(jnp.float32) + mm(h, take(fd.w_out)) + take(fd.b_out)

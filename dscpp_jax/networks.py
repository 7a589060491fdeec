"""Goal-conditioned actor and twin critic (Flax linen).

Both networks see the observation concatenated with the goal xy. The actor has two flavours:

* ``tanh``: the usual TD3 actor, ``max_action * tanh(W h + b)``;
* output normalisation (Agarwal et al. 2020, used by the model-based DSC++ variant): the linear
  output ``a`` divided by ``max(1, mean |a|)`` over the action dimensions.

The twin critic is one module whose parameters carry a leading axis of size 2 (``nn.vmap``), so
``TwinCritic.apply`` returns both Q heads as an array of shape ``(2, ...)`` in one fused call;
``first_head`` picks out the first head's parameters for a :class:`QNetwork` of the same widths.

The dynamics model lives in :mod:`dscpp_jax.dynamics`.
"""
from __future__ import annotations

from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def _edge_dtype(dtype: Any, io_dtype: Any) -> Any:
    """The dtype of the first and the output layer's products: ``io_dtype``, else ``dtype``."""
    return dtype if io_dtype is None else io_dtype


def _mlp_torso(x: jax.Array, hidden: Sequence[int], dtype: Any = None, io_dtype: Any = None) -> jax.Array:
    """ReLU layers; the first layer's product in ``_edge_dtype(dtype, io_dtype)``, every
    activation and later product in ``dtype`` (None: the inputs')."""
    for i, width in enumerate(hidden):
        layer_dtype = _edge_dtype(dtype, io_dtype) if i == 0 else dtype
        x = nn.Dense(width, dtype=layer_dtype, name=f"hidden_{i}")(x)
        if dtype is not None:
            x = x.astype(dtype)
        x = nn.relu(x)
    return x


def normalise_output(a: jax.Array) -> jax.Array:
    """Output normalisation: ``a / max(1, mean|a|)`` over the last axis."""
    scale = jnp.maximum(1.0, jnp.mean(jnp.abs(a), axis=-1, keepdims=True))
    return a / scale


class Actor(nn.Module):
    """Deterministic policy pi(obs, goal) -> action (any leading batch shape)."""

    action_dim: int
    hidden: Sequence[int] = (256, 256)
    output_normalisation: bool = False
    max_action: float = 1.0
    dtype: Any = None  # computation dtype of the layers (None: the inputs'); parameters float32
    io_dtype: Any = None  # of the first and the output layer's products (None: ``dtype``)

    @nn.compact
    def __call__(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, goal], axis=-1)
        x = _mlp_torso(x, self.hidden, self.dtype, self.io_dtype)
        a = nn.Dense(self.action_dim, dtype=_edge_dtype(self.dtype, self.io_dtype),
                     name="out")(x).astype(jnp.float32)
        if self.output_normalisation:
            return normalise_output(a)
        return self.max_action * jnp.tanh(a)


class QNetwork(nn.Module):
    """One Q head: Q(obs, goal, action) -> scalar (leading batch shape kept)."""

    hidden: Sequence[int] = (256, 256)
    dtype: Any = None
    io_dtype: Any = None

    @nn.compact
    def __call__(self, obs: jax.Array, goal: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, goal, action], axis=-1)
        x = _mlp_torso(x, self.hidden, self.dtype, self.io_dtype)
        out = nn.Dense(1, dtype=_edge_dtype(self.dtype, self.io_dtype), name="out")(x)
        return out[..., 0].astype(jnp.float32)


class TwinCritic(nn.Module):
    """Two independent Q heads; returns an array of shape ``(2, *batch)``."""

    hidden: Sequence[int] = (256, 256)
    num_heads: int = 2
    dtype: Any = None
    io_dtype: Any = None

    @nn.compact
    def __call__(self, obs: jax.Array, goal: jax.Array, action: jax.Array) -> jax.Array:
        heads = nn.vmap(
            QNetwork,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=self.num_heads,
        )
        return heads(hidden=self.hidden, dtype=self.dtype, io_dtype=self.io_dtype,
                     name="heads")(obs, goal, action)


def first_head(critic_params):
    """The parameters of a :class:`TwinCritic`'s first head, for :class:`QNetwork` (``Q1`` alone:
    the TD3 actor's loss needs no second head, and computing one costs as much as the first)."""
    return {"params": jax.tree_util.tree_map(lambda p: p[0], critic_params["params"]["heads"])}


def actor_action_dim(actor_params) -> int:
    """The action size of an actor, read from its parameters (a static shape)."""
    return int(actor_params["params"]["out"]["kernel"].shape[-1])

"""Sparse goal-conditioned reward and termination, shared by the ant and the point mass."""
from __future__ import annotations

import jax.numpy as jnp

GOAL_TOLERANCE = 0.6
EPISODE_LENGTH = 1000


def achieved_goal(obs):
    """The achieved goal of an observation: its torso / point (x, y) = obs[..., :2]."""
    return obs[..., :2]


def goal_reached(achieved, goal, tol: float = GOAL_TOLERANCE):
    """(..., 2), (..., 2) -> (...,) bool: ||achieved - goal|| <= tol."""
    return jnp.linalg.norm(achieved - goal, axis=-1) <= tol


def goal_reward(achieved, goal, tol: float = GOAL_TOLERANCE):
    """(..., 2), (..., 2) -> (...,) float32: 0 within `tol` of the goal, else -1."""
    return jnp.where(goal_reached(achieved, goal, tol), 0.0, -1.0).astype(jnp.float32)


def initial_info(goal, dtype=jnp.float32):
    """The info dict every env starts an episode with (fixed keys so lax.scan carries are stable)."""
    zero = jnp.zeros((), dtype)
    return {"goal": jnp.asarray(goal, dtype), "steps": jnp.zeros((), jnp.int32),
            "truncation": zero, "success": zero, "nan": zero, "overflow": zero}


def finish_step(info, obs, prev_obs, episode_length: int, tol: float, nan=None, overflow=None):
    """Shared step bookkeeping. Returns (obs, reward, done, info).

    nan: bool scalar, physics produced non-finite numbers -> obs replaced by `prev_obs`, reward 0,
    episode ends. done = success | truncation | nan; no auto-reset. overflow: bool scalar, the
    physics dropped contacts or constraints for want of buffer room (recorded in info["overflow"]).
    """
    if nan is None:
        nan = jnp.zeros((), bool)
    obs = jnp.where(nan, prev_obs, obs)
    steps = info["steps"] + 1
    success = goal_reached(achieved_goal(obs), info["goal"], tol) & ~nan
    truncation = (steps >= episode_length) & ~success & ~nan
    reward = jnp.where(nan, 0.0, goal_reward(achieved_goal(obs), info["goal"], tol))
    done = success | truncation | nan
    f = lambda b: b.astype(jnp.float32)
    over = jnp.zeros((), bool) if overflow is None else overflow
    info = dict(info, steps=steps, truncation=f(truncation), success=f(success), nan=f(nan),
                overflow=f(over))
    return obs, reward.astype(jnp.float32), f(done), info

"""Point-mass twin of the ant mazes, in pure JAX: same layouts, coordinates, goals, rewards, API.

Observation [x, y, vx, vy]; action in [-1, 1]^2 is an acceleration command. Per env step
(dt = 0.1 s):  v' = (1 - damping) v + accel * dt * a,  then the point moves by v' dt, axis by axis;
a move that would enter a wall (grown by `radius`) is shortened to the largest admissible fraction
and that velocity component is zeroed (sliding collision), so the point never ends in a wall.
With the defaults the top speed is accel*dt/damping = 3 units/s = 0.3 per step: one 4.0 cell takes
~13 steps, one 3.0 cell ~10.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from brax.envs.base import State

from dscpp_jax.envs import goals
from dscpp_jax.envs.goal_env import GoalMazeEnv
from dscpp_jax.envs.maze_layout import MazeLayout


@dataclasses.dataclass(frozen=True)
class PointConfig:
    dt: float = 0.1
    accel: float = 6.0
    damping: float = 0.2
    radius: float = 0.1
    reset_noise: float = 0.1
    episode_length: int = goals.EPISODE_LENGTH
    goal_tolerance: float = goals.GOAL_TOLERANCE
    start_margin: float = 0.5  # wall margin of the diverse-start sampler
    # Fractions of a blocked move that are tried (largest admissible one is taken).
    substeps: int = 16


class PointMazeEnv(GoalMazeEnv):
    """Brax-style env (reset/step over brax.envs.base.State); pipeline_state is None."""

    observation_size = 4
    action_size = 2
    backend = "jax"

    def __init__(self, layout: MazeLayout, config: PointConfig = PointConfig()):
        super().__init__(layout, config)
        self.name = "point_" + layout.name

    def __repr__(self):
        return f"PointMazeEnv({self.layout.name!r})"

    # ---- API ---------------------------------------------------------------------------------
    def reset_at(self, key, xy) -> State:
        """Episode with the point at xy (+ reset noise; noise that would enter a wall is dropped)."""
        xy = jnp.asarray(xy, jnp.float32)
        noise = jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0) * self.config.reset_noise
        pos = jnp.where(self.layout.in_wall(xy + noise, self.config.radius), xy, xy + noise)
        obs = jnp.concatenate([pos, jnp.zeros(2, jnp.float32)])
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=None, obs=obs, reward=zero, done=zero, metrics={},
                     info=goals.initial_info(self.goal))

    def step(self, state: State, action) -> State:
        c = self.config
        a = jnp.clip(jnp.nan_to_num(jnp.asarray(action, jnp.float32)), -1.0, 1.0)
        pos, vel = state.obs[:2], state.obs[2:]
        vel = (1.0 - c.damping) * vel + c.accel * c.dt * a
        fracs = jnp.linspace(1.0, 0.0, c.substeps + 1)  # 1, ..., 0 (0 is always admissible)
        for axis in range(2):  # static unrolled loop over the two axes
            moves = fracs * vel[axis] * c.dt
            cand = jnp.broadcast_to(pos, (fracs.shape[0], 2)).at[:, axis].add(moves)
            ok = ~self.layout.in_wall(cand, c.radius)
            ok = ok.at[-1].set(True)
            first = jnp.argmax(ok)
            pos = cand[first]
            vel = vel.at[axis].set(jnp.where(first == 0, vel[axis], 0.0))
        obs = jnp.concatenate([pos, vel])
        obs, reward, done, info = goals.finish_step(state.info, obs, state.obs, c.episode_length,
                                                    c.goal_tolerance)
        return state.replace(obs=obs, reward=reward, done=done, info=info)

"""What every goal-conditioned maze env shares: task start/goal, episode constants, diverse starts.

Subclasses set `observation_size`, `action_size`, `backend` and implement `reset_at(key, xy)` and
`step(state, action)` (brax.envs.base.State in and out); `goals.finish_step` does the reward,
termination and info bookkeeping of a step.
"""
import jax.numpy as jnp

from envs.maze_layout import MazeLayout


class GoalMazeEnv:
    """Base of the ant and point-mass mazes: a Brax-compatible, goal-conditioned interface."""

    goal_size = 2

    def __init__(self, layout: MazeLayout, config):
        self.layout = layout
        self.config = config
        self.episode_length = config.episode_length
        self.goal_tolerance = config.goal_tolerance
        self.start = jnp.asarray(layout.start_xy, jnp.float32)
        self.goal = jnp.asarray(layout.goal_xy, jnp.float32)

    @property
    def unwrapped(self):
        return self

    def reset(self, key):
        """Episode at the task start (with the env's reset noise)."""
        return self.reset_at(key, self.start)

    def reset_at(self, key, xy):
        raise NotImplementedError

    def step(self, state, action):
        raise NotImplementedError

    def upright(self, obs):
        """How upright the body is, in [-1, 1] (1: upright, below 0: upside down); (...,) from obs.

        A point mass cannot tip over, so the base class returns 1.
        """
        return jnp.ones(jnp.shape(obs)[:-1], jnp.float32)

    def sample_start(self, key):
        """Diverse start: uniform over free space, `start_margin` from walls, outside the goal region."""
        return self.layout.sample_free(key, self.goal, margin=self.config.start_margin,
                                       goal_tolerance=self.goal_tolerance)

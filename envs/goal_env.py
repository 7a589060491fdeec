"""What every goal-conditioned maze env shares: task start/goal, episode constants, diverse starts.

Subclasses set `observation_size`, `action_size`, `backend` and implement `reset_at(key, xy)` and
`step(state, action)` (brax.envs.base.State in and out); `goals.finish_step` does the reward,
termination and info bookkeeping of a step.
"""
import jax
import jax.numpy as jnp

from envs.maze_layout import MazeLayout


def select_state(pred, on_true, on_false):
    """`on_true` where `pred` else `on_false`, for one env's State (scalar `pred`; vmap it for a
    batch). MuJoCo Warp data keeps its contact and constraint arrays shared by all worlds, so its
    physics state merges with `mjx.Data.where`, which leaves those alone; everything else merges
    leaf by leaf."""
    def merge(t, f):
        if hasattr(f, "where") and hasattr(f, "qpos"):   # an mjx.Data
            return f.where(pred, t)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), t, f)
    ps = merge(on_true.pipeline_state, on_false.pipeline_state)
    rest = jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b),
                                  on_true.replace(pipeline_state=None),
                                  on_false.replace(pipeline_state=None))
    return rest.replace(pipeline_state=ps)


def select_states(pred, on_true, on_false):
    """`select_state` over a batch: `pred` (B,), States with a leading axis B."""
    return jax.vmap(select_state)(pred, on_true, on_false)


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

"""What every goal-conditioned maze env shares: task start/goal, episode constants, diverse starts.

Subclasses set `observation_size`, `action_size`, `backend` and implement `reset_at(key, xy)` and
`step(state, action)` (brax.envs.base.State in and out); `goals.finish_step` does the reward,
termination and info bookkeeping of a step.
"""
import jax
import jax.numpy as jnp

from dscpp_jax.envs.maze_layout import MazeLayout


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


def join_states(a, b, like):
    """Two batches of States (leading axes B and E) as one of B + E, shaped as `like` (the
    abstract joint batch, e.g. `jax.eval_shape` of a vmapped reset of an env sized for B + E
    worlds; its tree structure is the result's). Per-world leaves are concatenated; MuJoCo Warp's
    buffers shared by all worlds of a batch (contacts, sized by the worlds) are concatenated too,
    and its batch-wide counters (recomputed by every step) come from `a`. `split_states` undoes
    it, so two batches can take one physics step without either changing the other's results."""
    xs, ys = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    ls, treedef = jax.tree_util.tree_flatten(like)
    if not len(xs) == len(ys) == len(ls):
        raise ValueError("join_states: the two batches and `like` are different kinds of state")
    out = []
    for x, y, l in zip(xs, ys, ls):
        if x.ndim and x.ndim == y.ndim == len(l.shape) and x.shape[0] + y.shape[0] == l.shape[0]:
            out.append(jnp.concatenate([x, y], axis=0))
        elif x.shape == tuple(l.shape):
            out.append(x)
        else:
            raise ValueError(f"join_states: leaves of shapes {x.shape} and {y.shape} do not make "
                             f"one of {tuple(l.shape)}")
    return jax.tree_util.tree_unflatten(treedef, out)


def split_states(joint, like_a, like_b):
    """The inverse of `join_states`: the joint batch as batches shaped as `like_a` and `like_b`
    (trees of arrays or shapes); leaves that are batch-wide counters go to both."""
    zs = jax.tree_util.tree_leaves(joint)
    la, def_a = jax.tree_util.tree_flatten(like_a)
    lb, def_b = jax.tree_util.tree_flatten(like_b)
    if not len(zs) == len(la) == len(lb):
        raise ValueError("split_states: the joint batch and the parts are different kinds of state")
    out_a, out_b = [], []
    for z, x, y in zip(zs, la, lb):
        if z.ndim and len(x.shape) == len(y.shape) == z.ndim \
                and x.shape[0] + y.shape[0] == z.shape[0]:
            out_a.append(z[:x.shape[0]])
            out_b.append(z[x.shape[0]:])
        elif z.shape == tuple(x.shape) == tuple(y.shape):
            out_a.append(z)
            out_b.append(z)
        else:
            raise ValueError(f"split_states: a leaf of shape {z.shape} does not split into "
                             f"{tuple(x.shape)} and {tuple(y.shape)}")
    return jax.tree_util.tree_unflatten(def_a, out_a), jax.tree_util.tree_unflatten(def_b, out_b)


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

"""Small trainer configurations and tree comparisons shared by the trainer tests."""
import jax
import numpy as np

from dscpp_jax import checkpoint as ck
from dscpp_jax.config import preset


def tiny(algo="mf_dscpp", **kw):
    base = dict(num_envs=4, steps_per_iter=20, total_env_steps=10_000, episode_length=100,
                warmup_episodes=2, max_options=4, max_pos_traj=8, max_neg=8, buffer_len=10,
                option_timeout=40, gestation=2, td3_hidden=32, td3_batch_size=32,
                td3_updates_per_step=0.1, replay_capacity=2000, model_capacity=2000,
                dyn_hidden=16, dyn_batch_size=32, dyn_updates_per_step=0.05, dyn_pretrain_steps=5,
                mpc_samples=32, mpc_horizon=3, eval_episodes=2, eval_every=0, checkpoint_every=0)
    base.update(kw)
    return preset("fast", "point_u_maze", algo, **base)


def assert_trees_equal(a, b):
    la, ta = jax.tree_util.tree_flatten(ck.to_storable(a))
    lb, tb = jax.tree_util.tree_flatten(ck.to_storable(b))
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))

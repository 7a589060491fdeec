"""Whole-state checkpoints: round trip, and resume equivalence (N straight == N/2 + save + restore
+ N/2 on the same device with the same seed)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import checkpoint as ck
from dscpp_jax import trainer as T
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


def test_roundtrip_with_typed_keys(tmp_path):
    tree = {"a": jnp.arange(5.0), "k": jax.random.key(3), "raw": jax.random.PRNGKey(1),
            "flag": jnp.zeros((), bool), "none": None}
    ck.save_state(str(tmp_path), 7, tree)
    assert ck.latest_step(str(tmp_path)) == 7
    back = ck.restore_state(str(tmp_path), tree)
    assert jax.dtypes.issubdtype(back["k"].dtype, jax.dtypes.prng_key)
    np.testing.assert_array_equal(jax.random.key_data(back["k"]), jax.random.key_data(tree["k"]))
    np.testing.assert_array_equal(back["a"], tree["a"])
    with pytest.raises(FileNotFoundError):
        ck.restore_state(str(tmp_path / "missing"), tree)


@pytest.mark.parametrize("algo", ["mb_dscpp", "mf_dscpp"])
def test_resume_equivalence(tmp_path, algo):
    cfg = tiny(algo)
    s0 = T.init(jax.random.PRNGKey(3), cfg)
    straight = s0
    for _ in range(4):
        straight, _ = T.train_step(straight)
    half = s0
    for _ in range(2):
        half, _ = T.train_step(half)
    ck.save_state(str(tmp_path), int(half.counters.iteration), half)
    fresh = T.init(jax.random.PRNGKey(99), cfg)          # different contents, same structure
    resumed = ck.restore_state(str(tmp_path), fresh)
    assert_trees_equal(resumed, half)
    n_compiled = T.train_step._cache_size()
    for _ in range(2):
        resumed, _ = T.train_step(resumed)
    assert T.train_step._cache_size() == n_compiled   # a restored state does not recompile
    assert int(resumed.counters.iteration) == 4
    assert_trees_equal(resumed, straight)

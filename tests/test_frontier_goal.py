"""Frontier starts for the goal option (`frontier.goal_starts`): the pool next to the task goal
against a NumPy oracle, only while the goal option is in gestation, per seed under vmap; off by
default it changes nothing."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import acting
from dscpp_jax import frontier as F
from dscpp_jax import options as O
from dscpp_jax import trainer as T
from dscpp_jax.cli import parse_overrides
from dscpp_jax.config import Config
from tests.trainer_fixtures import tiny

GOAL_XY = np.array([0.0, 8.0], np.float32)
CFG = O.ChainConfig(max_options=5, gestation=3, buffer_len=5, max_pos_traj=6, max_neg=4)
A, G, M, FR = O.ALWAYS, O.GESTATION, O.MATURE, O.FREE
GRID = np.stack(np.meshgrid(np.linspace(-9, 9, 19), np.linspace(-9, 12, 22)), -1)
CAND = GRID.reshape(-1, 2).astype(np.float32)
pool_of = jax.jit(F.goal_pool, static_argnums=(2, 3))


def _successes(chain, option, center, n, seed):
    rng = np.random.default_rng(seed)
    B, T_ = 8, chain.cfg.buffer_len
    start = (np.asarray(center) + rng.uniform(-1, 1, (B, 2))).astype(np.float32)
    traj = (np.asarray(center) + rng.uniform(-1, 1, (B, T_, 2))).astype(np.float32)
    ev = np.arange(B) < n
    return jax.jit(O.record_outcomes)(chain, np.full((B,), option, np.int32), ev, start, traj,
                                      np.ones((B, T_), bool), ev)


def test_the_goal_pool_is_the_annulus_round_the_goal_while_the_goal_option_is_in_gestation():
    ch = O.chain_init(CFG, GOAL_XY)
    assert int(ch.status[O.GOAL]) == G
    got = np.asarray(pool_of(ch, CAND, 6.0, 3.0))
    d = np.linalg.norm(CAND - GOAL_XY, axis=-1)
    np.testing.assert_array_equal(got, (d <= 6.0) & (d >= 3.0))
    assert 0 < got.sum() < len(CAND)
    # inner radius 0: the whole disc
    np.testing.assert_array_equal(np.asarray(pool_of(ch, CAND, 6.0, 0.0)), d <= 6.0)
    # the goal option mature: empty
    mature = O.refit(_successes(ch, O.GOAL, (0.0, 7.0), 5, seed=1))
    mature = O.mature_options(mature)
    assert int(mature.status[O.GOAL]) == M
    assert not np.asarray(pool_of(mature, CAND, 6.0, 3.0)).any()
    with pytest.raises(ValueError, match="inner < radius"):
        F.goal_pool(ch, CAND, 3.0, 3.0)
    with pytest.raises(ValueError, match=r"\(M, 2\)"):
        F.goal_pool(ch, CAND[:, :1], 6.0, 3.0)


def test_per_seed_pools_under_vmap():
    fresh = O.chain_init(CFG, GOAL_XY)
    mature = O.mature_options(O.refit(_successes(fresh, O.GOAL, (0.0, 7.0), 5, seed=1)))
    seeds = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), fresh, mature)
    got = np.asarray(jax.jit(jax.vmap(lambda c: F.goal_pool(c, CAND, 6.0, 3.0)))(seeds))
    np.testing.assert_array_equal(got[0], np.asarray(F.goal_pool(fresh, CAND, 6.0, 3.0)))
    assert got[0].any() and not got[1].any()


def test_off_by_default_and_the_trainer_pool_adds_the_goal_pool():
    assert Config().frontier.goal_starts is False
    cfg = tiny("mb_dscpp", frontier_start_prob=0.5, frontier_radius=4.0,
               frontier_inner_radius=1.0, frontier_candidates=256)
    env = T.make_env(cfg)
    key = jax.random.PRNGKey(0)
    ch = T.init(jax.random.PRNGKey(1), cfg).chain     # the goal option in gestation
    cand, off = acting.frontier_pool(cfg, env, ch, key)
    assert not np.asarray(off).any()          # no mature option: no frontier yet
    on = cfg.override(frontier_goal_starts=True)
    cand2, pool = jax.jit(lambda c, k: acting.frontier_pool(on, env, c, k))(ch, key)
    np.testing.assert_array_equal(np.asarray(cand2), np.asarray(cand))
    np.testing.assert_array_equal(np.asarray(pool), np.asarray(F.goal_pool(ch, cand, 4.0, 1.0)))
    assert np.asarray(pool).any()


def test_training_with_goal_starts_draws_them_until_the_goal_option_matures():
    cfg = tiny("mf_dscpp", frontier_start_prob=0.5, frontier_parent=True, frontier_candidates=64,
               frontier_radius=4.0, frontier_inner_radius=1.0, frontier_min_open=2)
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    pools = []
    for c in (cfg, cfg.override(frontier_goal_starts=True)):
        states = jax.vmap(lambda k: T.init(k, c))(keys)
        states, m = jax.jit(T.train_step_group_impl)(states)
        assert (np.asarray(states.chain.status[:, O.GOAL]) == G).all()
        pools.append(np.asarray(m["frontier/pool"]))
    np.testing.assert_array_equal(pools[0], [0.0, 0.0])
    assert (pools[1] > 0).all()


def test_the_flat_and_dotted_names_are_accepted_and_bad_settings_refused():
    assert parse_overrides(["frontier_goal_starts=true"]) == {"frontier_goal_starts": True}
    assert parse_overrides(["frontier.goal_starts=false"]) == {"frontier_goal_starts": False}
    c = tiny("mb_dscpp", frontier_start_prob=0.5, frontier_goal_starts=True).validate()
    assert c.frontier.goal_starts is True
    with pytest.raises(ValueError, match="frontier_start_prob > 0"):
        tiny("mb_dscpp", frontier_parent=True, frontier_goal_starts=True).validate()
    # inert where frontier starts are off
    assert "frontier_goal_starts" in tiny("mb_dscpp", frontier_parent=True).inert_fields()
    assert "frontier_goal_starts" not in tiny("mb_dscpp",
                                              frontier_start_prob=0.5).inert_fields()

"""Frontier starts close in on a stalled link (`frontier.shrink_executions`): the start pool's
radii shrink after exactly N failed executions of the link in gestation, floor, come back when
the link matures or a new one starts, per seed under vmap; off by default it changes nothing."""
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
from tests.trainer_fixtures import assert_trees_equal, tiny

GOAL_XY = np.array([0.0, 8.0], np.float32)
CFG = O.ChainConfig(max_options=5, gestation=3, buffer_len=5, max_pos_traj=6, max_neg=4)
A, G, M, FR = O.ALWAYS, O.GESTATION, O.MATURE, O.FREE
record = jax.jit(O.record_outcomes)


def _successes(chain, option, center, n, seed):
    rng = np.random.default_rng(seed)
    B, T_ = 8, chain.cfg.buffer_len
    start = (np.asarray(center) + rng.uniform(-1, 1, (B, 2))).astype(np.float32)
    traj = (np.asarray(center) + rng.uniform(-1, 1, (B, T_, 2))).astype(np.float32)
    ev = np.arange(B) < n
    return record(chain, np.full((B,), option, np.int32), ev, start, traj, np.ones((B, T_), bool), ev)


def _failures(chain, option, n):
    """`n` failed executions of `option`, 8 at a time (the counters only)."""
    B, T_ = 8, chain.cfg.buffer_len
    for i in range(0, n, B):
        ev = np.arange(B) < min(B, n - i)
        chain = record(chain, np.full((B,), option, np.int32), np.zeros(B, bool),
                       np.zeros((B, 2), np.float32), np.zeros((B, T_, 2), np.float32),
                       np.ones((B, T_), bool), ev)
    return chain


@pytest.fixture(scope="module")
def chain():
    """Goal option mature near the goal, link 2 mature at (0, 4), link 3 in gestation targeting
    it with 1 success; fitted."""
    ch = O.chain_init(CFG, GOAL_XY)
    ch = ch.replace(status=jnp.array([A, M, M, G, FR]), parent=jnp.array([-1, -1, 1, 2, -1]),
                    num_options=jnp.asarray(4))
    ch = _successes(ch, 1, (0.0, 7.0), 5, seed=1)
    ch = _successes(ch, 2, (0.0, 4.0), 5, seed=2)
    ch = _successes(ch, 3, (0.0, 0.5), 1, seed=3)
    return jax.jit(O.refit)(ch)


scale = jax.jit(F.shrink_scale, static_argnums=(1, 2))


def test_the_radius_shrinks_after_exactly_n_failed_executions_and_floors(chain):
    assert float(scale(chain, 10, 0.5)) == 1.0          # 1 success, no failure yet
    got = []
    ch = chain
    for _ in range(60):
        ch = _failures(ch, 3, 1)
        got.append(float(scale(ch, 10, 0.5)))
    # failures 1..60: 1 up to 9, 0.5 from the 10th, 0.25 from the 20th, then the floor (1/8)
    want = [0.5 ** min(n // 10, 3) for n in range(1, 61)]
    assert got == want
    assert F.SHRINK_FLOOR == 0.125 and got[-1] == F.SHRINK_FLOOR
    # successes do not count as failures: 60 failures and 1 success still give the floor
    assert int(ch.executions[3]) == 61 and int(ch.successes[3]) == 1
    # off (every <= 0): always 1
    assert float(scale(ch, 0, 0.5)) == 1.0


def test_the_radius_resets_when_the_link_matures_or_a_new_link_starts(chain):
    ch = _failures(chain, 3, 25)
    assert float(scale(ch, 10, 0.5)) == 0.25
    # two more successes: link 3 matures (gestation 3); no link is in gestation: configured radii
    ch = jax.jit(O.refit)(_successes(ch, 3, (0.0, 0.5), 2, seed=4))
    matured = O.mature_options(ch)
    assert int(matured.status[3]) == M
    assert float(scale(matured, 10, 0.5)) == 1.0
    # a new link 4 (targeting 3, a free row until now): its counters start at 0, the radii at the
    # configured ones
    grown = matured.replace(status=matured.status.at[4].set(G),
                            parent=matured.parent.at[4].set(3), num_options=jnp.asarray(5))
    assert int(grown.status[4]) == G and int(grown.executions[4]) == 0
    assert float(scale(grown, 10, 0.5)) == 1.0
    assert float(scale(_failures(grown, 4, 10), 10, 0.5)) == 0.5
    # a re-targeted link's counters are cleared: back at 1 too
    cleared = O.clear_row(ch, 3, True)
    assert float(scale(cleared, 10, 0.5)) == 1.0


def test_per_seed_scales_under_vmap_and_a_traced_probe_matches_the_static_one(chain):
    seeds = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), chain, _failures(chain, 3, 10),
                                   _failures(chain, 3, 40))
    s = jax.jit(jax.vmap(lambda c: F.shrink_scale(c, 10, 0.5)))(seeds)
    np.testing.assert_array_equal(np.asarray(s), [1.0, 0.5, 0.125])
    grid = np.stack(np.meshgrid(np.linspace(-9, 9, 19), np.linspace(-9, 12, 22)), -1)
    cand = jnp.asarray(grid.reshape(-1, 2), jnp.float32)
    traced = jax.jit(jax.vmap(lambda c, k: F.frontier_probe(c, cand, 6.0 * k, 3.0 * k)))(seeds, s)
    for i, k in enumerate((1.0, 0.5, 0.125)):
        one = jax.tree_util.tree_map(lambda x: x[i], seeds)
        np.testing.assert_array_equal(np.asarray(traced[i]),
                                      np.asarray(F.frontier_probe(one, cand, 6.0 * k, 3.0 * k)))
    # the shrink matters here: fewer frontier candidates at half the radii
    assert int(traced[1].sum()) < int(traced[0].sum())


def test_off_by_default_and_the_pool_uses_the_shrunk_radii(chain):
    assert Config().frontier.shrink_executions == 0
    cfg = tiny("mb_dscpp", frontier_start_prob=0.5, frontier_radius=6.0,
               frontier_inner_radius=3.0, frontier_candidates=256)
    env = T.make_env(cfg)
    key = jax.random.PRNGKey(0)
    ch = _failures(chain, 3, 20)
    cand, pool = acting.frontier_pool(cfg, env, ch, key)
    want = F.start_pool(ch, F.frontier_probe(ch, cand, 6.0, 3.0))
    np.testing.assert_array_equal(np.asarray(pool), np.asarray(want))
    on = cfg.override(frontier_shrink_executions=10, frontier_shrink_factor=0.5)
    cand2, pool2 = jax.jit(lambda c, k: acting.frontier_pool(on, env, c, k))(ch, key)
    np.testing.assert_array_equal(np.asarray(cand2), np.asarray(cand))
    want = F.start_pool(ch, F.frontier_probe(ch, cand, 1.5, 0.75))
    np.testing.assert_array_equal(np.asarray(pool2), np.asarray(want))


def test_training_with_a_shrink_that_never_fires_equals_training_without_one():
    # the traced radii path at scale 1 gives the same numbers as the configured radii path, and
    # the shrink adds one metric, per seed
    cfg = tiny("mf_dscpp", frontier_start_prob=0.5, frontier_parent=True, frontier_candidates=64,
               frontier_radius=4.0, frontier_inner_radius=1.0, frontier_min_open=2)
    never = cfg.override(frontier_shrink_executions=10 ** 6)
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    out = []
    for c in (cfg, never):
        states = jax.vmap(lambda k: T.init(k, c))(keys)
        step = jax.jit(T.train_step_group_impl)
        for _ in range(6):
            states, m = step(states)
        out.append((states, m))
    assert_trees_equal(out[0][0].chain, out[1][0].chain)
    np.testing.assert_array_equal(np.asarray(out[0][0].env_state.obs),
                                  np.asarray(out[1][0].env_state.obs))
    assert "frontier/radius_scale" not in out[0][1]
    np.testing.assert_array_equal(np.asarray(out[1][1]["frontier/radius_scale"]), [1.0, 1.0])


def test_the_flat_and_dotted_names_are_accepted():
    assert parse_overrides(["frontier_shrink_executions=100", "frontier.shrink_factor=0.25"]) == {
        "frontier_shrink_executions": 100, "frontier_shrink_factor": 0.25}
    c = tiny("mb_dscpp", frontier_start_prob=0.5, frontier_shrink_executions=100).validate()
    assert (c.frontier.shrink_executions, c.frontier.shrink_factor) == (100, 0.5)


@pytest.mark.parametrize("kw, match", [
    (dict(frontier_start_prob=0.5, frontier_shrink_executions=-1), "frontier_shrink_executions"),
    (dict(frontier_start_prob=0.5, frontier_shrink_factor=0.0), "frontier_shrink_factor"),
    (dict(frontier_start_prob=0.5, frontier_shrink_factor=1.0), "frontier_shrink_factor"),
    (dict(frontier_start_prob=0.0, frontier_shrink_executions=100), "frontier_start_prob > 0"),
])
def test_bad_shrink_settings_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        tiny("mb_dscpp", **kw).validate()

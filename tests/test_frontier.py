"""The chain's frontier: the probe against a NumPy oracle, re-targeting and parents in grow_chain,
frontier starts in the trainer."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import acting
from dscpp_jax import frontier as F
from dscpp_jax import options as O
from dscpp_jax import trainer as T
from tests.trainer_fixtures import tiny

GOAL_XY = np.array([0.0, 8.0], np.float32)
START_XY = np.array([0.0, -8.0], np.float32)
CFG = O.ChainConfig(max_options=5, gestation=3, buffer_len=5, max_pos_traj=6, max_neg=4)
A, G, M, FR = O.ALWAYS, O.GESTATION, O.MATURE, O.FREE

record = jax.jit(O.record_outcomes)
refit = jax.jit(O.refit)


def _successes(chain, option, center, n, seed):
    rng = np.random.default_rng(seed)
    B, T_ = 8, chain.cfg.buffer_len
    start = (np.asarray(center) + rng.uniform(-1, 1, (B, 2))).astype(np.float32)
    traj = (np.asarray(center) + rng.uniform(-1, 1, (B, T_, 2))).astype(np.float32)
    ids = np.full((B,), option, np.int32)
    ev = np.arange(B) < n
    return record(chain, ids, ev, start, traj, np.ones((B, T_), bool), ev)


@pytest.fixture(scope="module")
def two_links():
    """Goal option (row 1) mature near the goal, link 2 mature at (0, 4) targeting it, link 3 in
    gestation targeting link 2 with 2 successes near (0, 0); all fitted."""
    ch = O.chain_init(CFG, GOAL_XY)
    ch = ch.replace(status=jnp.array([A, M, M, G, FR]), parent=jnp.array([-1, -1, 1, 2, -1]),
                    num_options=jnp.asarray(4))
    ch = _successes(ch, 1, (0.0, 7.0), 5, seed=1)
    ch = _successes(ch, 2, (0.0, 4.0), 5, seed=2)
    ch = _successes(ch, 3, (0.0, 0.5), 2, seed=3)
    return refit(ch)


def test_probe_matches_a_numpy_oracle(two_links):
    ch = two_links
    grid = np.stack(np.meshgrid(np.linspace(-9, 9, 19), np.linspace(-9, 12, 22)), -1)
    cand = grid.reshape(-1, 2).astype(np.float32)
    radius = 3.0
    got = np.asarray(jax.jit(F.frontier_probe, static_argnums=2)(ch, cand, radius))
    assert got.shape == (CFG.max_options, len(cand))
    covered = np.array([bool(O.start_covered(ch, c)) for c in cand])
    want = np.zeros_like(got)
    for k in range(CFG.max_options):
        if int(ch.status[k]) != M:
            continue
        ok = np.asarray(ch.pess_ok[k]).reshape(-1)
        pts = np.asarray(ch.pos_xy[k]).reshape(-1, 2)[ok]
        d = np.linalg.norm(cand[:, None] - pts[None], axis=-1).min(axis=1)
        want[k] = (d <= radius) & ~covered
        inner_want = (d <= radius) & (d >= 1.5) & ~covered
        np.testing.assert_array_equal(np.asarray(F.frontier_probe(ch, cand, radius, 1.5))[k],
                                      inner_want)
    np.testing.assert_array_equal(got, want)
    # both mature rows have some frontier here, rows in gestation / free / global none
    assert want[1].any() and want[2].any() and not want[[0, 3, 4]].any()
    # the pool of frontier starts is the frontier of the row that the link in gestation targets
    np.testing.assert_array_equal(F.start_pool(ch, jnp.asarray(got)), want[2])
    np.testing.assert_array_equal(F.open_rows(jnp.asarray(got), 1), want.any(axis=1))


def test_probe_refuses_bad_input(two_links):
    with pytest.raises(ValueError, match="shape"):
        F.frontier_probe(two_links, np.zeros((3,), np.float32), 1.0)
    with pytest.raises(ValueError, match="radius"):
        F.frontier_probe(two_links, np.zeros((3, 2), np.float32), 0.0)
    with pytest.raises(ValueError, match="inner"):
        F.frontier_probe(two_links, np.zeros((3, 2), np.float32), 1.0, 2.0)


def _grow_with(chain, is_open):
    return jax.jit(F.grow_chain)(chain, START_XY, jnp.asarray(is_open))


def test_a_link_whose_target_frontier_closed_is_retargeted(two_links):
    ch = two_links
    assert int(ch.successes[3]) == 2 and bool(ch.fitted[3])
    # link 2 (the target of link 3) closed, the goal option open: link 3 now targets row 1 and
    # forgets what it learned about reaching link 2
    out = _grow_with(ch, [False, True, False, False, False])
    np.testing.assert_array_equal(out.status, [A, M, M, G, FR])
    np.testing.assert_array_equal(out.parent, [-1, -1, 1, 1, -1])
    assert int(out.successes[3]) == 0 and int(out.executions[3]) == 0
    assert not bool(out.pos_mask[3].any()) and not bool(out.fitted[3])
    assert not bool(out.pess_ok[3].any()) and int(out.pos_count[3]) == 0
    # the other rows are untouched
    for name in ("pos_xy", "pos_mask", "successes", "fitted"):
        np.testing.assert_array_equal(np.asarray(getattr(out, name))[:3],
                                      np.asarray(getattr(ch, name))[:3])
    # an open target, or no open row to go to: nothing changes
    for is_open in ([False, True, True, False, False], [False] * 5):
        same = _grow_with(ch, is_open)
        np.testing.assert_array_equal(same.parent, ch.parent)
        assert int(same.successes[3]) == 2 and bool(same.fitted[3])


def test_a_new_option_targets_the_newest_open_row(two_links):
    # link 3 matures (one more success); the chain then grows a link 4, whose parent is the newest
    # mature row with an open frontier (row 2 closed here: the goal option), not the newest (3)
    ch = refit(_successes(two_links, 3, (0.0, 0.5), 1, seed=4))
    plain = jax.jit(O.grow_chain)(ch, START_XY)
    np.testing.assert_array_equal(plain.status, [A, M, M, M, G])
    assert int(plain.parent[4]) == 3
    out = _grow_with(ch, [False, True, False, False, False])
    np.testing.assert_array_equal(out.status, [A, M, M, M, G])
    assert int(out.parent[4]) == 1
    # no open row: the newest, as in the paper
    assert int(_grow_with(ch, [False] * 5).parent[4]) == 3


def test_diverse_starts_take_the_frontier_share():
    cfg = tiny("mb_dscpp", num_envs=64, frontier_start_prob=0.5, task_start_prob=0.25)
    env = T.make_env(cfg)
    cand = np.stack([np.arange(8) + 100.0, np.zeros(8)], -1).astype(np.float32)  # off the maze
    pool = np.array([0, 1, 0, 1, 0, 0, 0, 1], bool)
    key = jax.random.PRNGKey(3)
    xy = np.asarray(acting.diverse_starts(cfg, env, key, 64, (jnp.asarray(cand), jnp.asarray(pool))))
    from_pool = xy[:, 0] >= 100
    assert set(xy[from_pool, 0]) <= {101.0, 103.0, 107.0}
    # the same uniform as task_start_prob: [task start | frontier | diverse] = [.25 | .5 | .25]
    u = np.asarray(jax.random.uniform(jax.random.fold_in(key, 1), (64,)))
    np.testing.assert_array_equal(from_pool, (u >= 0.25) & (u < 0.75))
    # the diverse ones are the sampler's, unchanged
    plain = np.asarray(acting.diverse_starts(cfg, env, key, 64))
    np.testing.assert_array_equal(xy[~from_pool], plain[~from_pool])
    # an empty pool: every start is the sampler's
    none = acting.diverse_starts(cfg, env, key, 64, (jnp.asarray(cand), jnp.zeros(8, bool)))
    np.testing.assert_array_equal(np.asarray(none), plain)


def test_training_with_the_frontier_runs_and_groups_equal_separate_runs():
    # both uses on, under a seed vmap and alone (the logic itself: the tests above)
    cfg = tiny("mf_dscpp", frontier_start_prob=0.5, frontier_parent=True, frontier_candidates=64,
               frontier_radius=4.0, frontier_min_open=2)
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    states = jax.vmap(lambda k: T.init(k, cfg))(keys)
    vstep = jax.jit(T.train_step_group_impl)
    for _ in range(8):      # past the warm-up, into chain growth
        states, vm = vstep(states)
    for name in ("frontier/retargeted", "frontier/open_rows", "frontier/pool"):
        assert np.all(np.isfinite(np.asarray(vm[name])))
    s = T.init(keys[1], cfg)
    for _ in range(8):
        s, m = T.train_step(s)
    np.testing.assert_array_equal(np.asarray(states.chain.parent[1]), np.asarray(s.chain.parent))
    np.testing.assert_allclose(np.asarray(states.env_state.obs[1]), np.asarray(s.env_state.obs),
                               rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kw, match", [
    (dict(frontier_start_prob=1.5), "frontier_start_prob"),
    (dict(frontier_start_prob=0.6, task_start_prob=0.6), "sum to at most 1"),
    (dict(frontier_start_prob=0.5, diverse_starts=False), "diverse_starts"),
    (dict(frontier_radius=0.0), "frontier_radius"),
    (dict(frontier_inner_radius=5.0, frontier_radius=5.0), "frontier_inner_radius"),
    (dict(frontier_candidates=0), "frontier_candidates"),
])
def test_bad_frontier_settings_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        tiny("mb_dscpp", **kw).validate()


def test_frontier_needs_a_skill_chain():
    with pytest.raises(ValueError, match="skill chain"):
        tiny("td3_her", frontier_parent=True).validate()

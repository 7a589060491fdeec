"""Subgoals: robust sampling from the parent's pessimistic region, and the Algorithm 1 DP table."""
import numpy as np
import jax
import jax.numpy as jnp
import pytest

from dscpp_jax import options as O
from dscpp_jax import subgoals as S

GOAL_XY = np.array([0.0, 8.0], np.float32)
START_XY = np.array([0.0, 0.0], np.float32)
CFG = O.ChainConfig(max_options=5, gestation=3, buffer_len=5, max_pos_traj=6, max_neg=4)
TOL = CFG.subgoal_tolerance
SHIFTS = np.array([[0, 0], [TOL, 0], [-TOL, 0], [0, TOL], [0, -TOL]], np.float32)

robust_many = jax.jit(jax.vmap(S.robust_subgoal_with_source, in_axes=(0, None, None)))


def _chain_with_link(spread, seed=0):
    """Goal option mature (successes near (0, 7) with the given spread), link 2 in gestation."""
    rng = np.random.default_rng(seed)
    B, T = CFG.max_pos_traj, CFG.buffer_len          # successes only: one-class classifiers
    ch = O.chain_init(CFG, GOAL_XY)
    center = np.array([0.0, 7.0], np.float32)
    start = (center + rng.uniform(-spread, spread, (B, 2))).astype(np.float32)
    traj = (center + rng.uniform(-spread, spread, (B, T, 2))).astype(np.float32)
    ch = jax.jit(O.record_outcomes)(ch, np.ones(B, np.int32), np.ones(B, bool),
                                    start, traj, rng.random((B, T)) < 0.8, np.ones(B, bool))
    ch = jax.jit(O.grow_chain)(jax.jit(O.refit)(ch), START_XY)
    assert int(ch.status[2]) == O.GESTATION and int(ch.parent[2]) == 1
    return ch


def _inside_parent(ch, pts):
    from dscpp_jax import initiation as I

    row = jax.tree_util.tree_map(lambda a: a[1], ch.clf)
    return np.asarray(I.pessimistic_contains(row, jnp.asarray(pts, jnp.float32)))


@pytest.fixture(scope="module")
def wide_chain():
    return _chain_with_link(spread=1.5)


def test_robust_subgoal_neighbourhood_inside_parent(wide_chain):
    ch = wide_chain
    keys = jax.random.split(jax.random.key(0), 64)
    xy, src = robust_many(keys, ch, 2)
    xy, src = np.asarray(xy), np.asarray(src)
    assert (src == S.SRC_ROBUST).all()
    # every answer: itself and xy +- tol along each axis inside the parent's pessimistic region
    pts = xy[:, None, :] + SHIFTS[None]
    assert _inside_parent(ch, pts.reshape(-1, 2)).all()
    # ... it is a stored positive state of the parent, the first qualifying one of its trajectory
    pos = np.asarray(ch.pos_xy[1])
    mask = np.asarray(ch.pos_mask[1])
    ok = _inside_parent(ch, (pos[:, :, None, :] + SHIFTS).reshape(-1, 2)).reshape(mask.shape + (5,))
    ok = ok.all(-1) & mask
    np.testing.assert_array_equal(ch.robust_ok[1], ok)         # the cache refit left behind
    chosen = set()
    for p in xy:
        hits = np.argwhere(np.all(pos == p, axis=-1) & mask)
        assert len(hits), p
        t, i = hits[0]
        assert ok[t, i] and not ok[t, :i].any()
        chosen.add(int(t))
    assert chosen == set(np.flatnonzero(ok.any(1)).tolist())   # every qualifying trajectory
    assert ok.sum() < mask.sum()                 # the test data has states that do not qualify


def test_robust_subgoal_fallback_to_pessimistic_region():
    ch = _chain_with_link(spread=0.05, seed=1)   # a region too small for a +-0.6 neighbourhood
    pos = np.asarray(ch.pos_xy[1])
    mask = np.asarray(ch.pos_mask[1])
    ok = _inside_parent(ch, (pos[:, :, None, :] + SHIFTS).reshape(-1, 2)).reshape(mask.shape + (5,))
    assert not (ok.all(-1) & mask).any()
    assert (ok[..., 0] & mask).any()
    xy, src = robust_many(jax.random.split(jax.random.key(1), 16), ch, 2)
    assert (np.asarray(src) == S.SRC_PESSIMISTIC).all()
    assert _inside_parent(ch, np.asarray(xy)).all()


def test_goal_and_global_option_target_the_task_goal(wide_chain):
    for o in (O.GLOBAL, O.GOAL):
        xy, src = S.robust_subgoal_with_source(jax.random.key(0), wide_chain, o)
        np.testing.assert_array_equal(xy, GOAL_XY)
        assert int(src) == S.SRC_TASK_GOAL


# ------------------------------------------------------------------------------------------------
# the DP value table (Algorithm 1)

def _value_np(obs, g):
    """A hand-written V(s | g): minus the distance, scaled by a non-xy entry of the state."""
    return -np.linalg.norm(obs[:2] - g) * (1.0 + 0.1 * obs[2])


def _value_jax(obs, g):
    return -jnp.linalg.norm(obs[:, :2] - g, axis=-1) * (1.0 + 0.1 * obs[:, 2])


def _synthetic_chain(seed=0):
    cfg = CFG.replace(obs_dim=3, buffer_len=2)
    K, P = cfg.max_options, cfg.max_pos_traj
    rng = np.random.default_rng(seed)
    ch = O.chain_init(cfg, GOAL_XY)
    pos_xy = np.zeros((K, P, cfg.traj_len, 2), np.float32)
    pos_xy[:, :, 0] = rng.uniform(-6, 10, (K, P, 2))
    pos_xy[1, 0, 0] = GOAL_XY + 0.2                         # an input already at the goal
    pos_xy[2, 1, 0] = pos_xy[1, 2, 0] + 0.1                 # an input already at an output
    pos_mask = np.zeros((K, P, cfg.traj_len), bool)
    pos_mask[:, :, 0] = rng.random((K, P)) < 0.8
    pos_mask[:, 0, 0] = True
    pos_mask[1, 2, 0] = pos_mask[2, 1, 0] = True
    pos_obs = np.concatenate([pos_xy[:, :, 0], rng.uniform(0, 2, (K, P, 1))], -1).astype(np.float32)
    pess_ok = np.zeros((K, P, cfg.traj_len), bool)
    pess_ok[:, :, 0] = rng.random((K, P)) < 0.6
    pess_ok[1, 2, 0] = True
    pess_ok[3, :, 0] = False                                # option 4's parent: no output qualifies
    ch = ch.replace(status=jnp.array([O.ALWAYS, O.MATURE, O.MATURE, O.MATURE, O.GESTATION]),
                    parent=jnp.array([-1, -1, 1, 2, 3]), num_options=jnp.asarray(5),
                    pos_xy=jnp.asarray(pos_xy), pos_mask=jnp.asarray(pos_mask),
                    pos_obs=jnp.asarray(pos_obs), pess_ok=jnp.asarray(pess_ok))
    return ch


def _ref_dp(ch, gamma=0.95, tol=TOL, goal_value=0.0, value_np=None):
    """Algorithm 1 with plain loops: returns {option: (outputs, cont, Q (inputs x outputs))}.
    ``value_np(option, obs, g)``: a value function per option (default `_value_np` for all)."""
    value_np = value_np or (lambda o, s, g: _value_np(s, g))
    parent = np.asarray(ch.parent)
    xy = np.asarray(ch.pos_xy[:, :, 0])
    obs = np.asarray(ch.pos_obs)
    valid = np.asarray(ch.pos_mask[:, :, 0])
    pess = np.asarray(ch.pess_ok[:, :, 0])
    W, out = {}, {}
    for o in range(1, int(ch.num_options)):
        if o == O.GOAL:
            outs = [(0, GOAL_XY, goal_value)]
        else:
            p = parent[o]
            js = [j for j in range(len(valid[p])) if valid[p, j] and pess[p, j]]
            if not js:
                js = [j for j in range(len(valid[p])) if valid[p, j]]
            outs = [(j, xy[p, j], W[p][j]) for j in js]
        Q, W[o] = {}, {}
        for i in range(len(valid[o])):
            if not valid[o, i]:
                continue
            for j, s2, cont in outs:
                same = np.linalg.norm(xy[o, i] - s2) <= tol
                Q[i, j] = (0.0 if same else value_np(o, obs[o, i], s2)) + gamma * cont
            W[o][i] = max(Q[i, j] for j, _, _ in outs)
        out[o] = (outs, Q)
    return out


def _per_option_np(o, s, g):
    return _value_np(s, g) * (1.0 + 0.5 * o)


def _per_option_jax(o, s, g):
    return _value_jax(s, g) * (1.0 + 0.5 * o)


@pytest.mark.parametrize("per_option", [False, True], ids=["shared", "per_option"])
def test_dp_table_matches_reference(per_option):
    """Also with one value function per option (`option_value_fn`, one critic per option): each
    option's row is valued with its own."""
    ch = _synthetic_chain()
    if per_option:
        table = jax.jit(lambda c: S.dp_value_table(c, None, option_value_fn=_per_option_jax))(ch)
        ref = _ref_dp(ch, value_np=_per_option_np)
    else:
        table = jax.jit(S.dp_value_table, static_argnums=1)(ch, _value_jax)
        ref = _ref_dp(ch)
    q = np.asarray(table.q)
    for o, (outs, Q) in ref.items():
        out_idx = [j for j, _, _ in outs]
        np.testing.assert_array_equal(np.flatnonzero(table.out_mask[o]), out_idx, err_msg=f"o={o}")
        for j, s2, cont in outs:
            np.testing.assert_allclose(table.out_xy[o, j], s2, rtol=1e-6)
            np.testing.assert_allclose(table.cont[o, j], cont, rtol=1e-5, atol=1e-5)
        for (i, j), v in Q.items():
            np.testing.assert_allclose(q[o, i, j], v, rtol=1e-5, atol=1e-5, err_msg=f"o={o} i={i} j={j}")
        n_valid = np.asarray(table.in_mask[o]).sum() * len(outs)
        assert (q[o] > S.NEG / 2).sum() == n_valid == len(Q)
    assert 4 in ref and len(ref[4][0]) > 0                  # the fallback output set was used


def test_pick_subgoal_matches_reference():
    ch = _synthetic_chain(seed=3)
    table = S.dp_value_table(ch, _value_jax)
    ref = _ref_dp(ch)
    pick = jax.jit(jax.vmap(lambda o, s: S.pick_subgoal(table, ch, o, s, _value_jax),
                            in_axes=(None, 0)))
    rng = np.random.default_rng(0)
    obs = np.concatenate([rng.uniform(-6, 10, (20, 2)), rng.uniform(0, 2, (20, 1))], -1)
    obs = obs.astype(np.float32)
    obs[0, :2] = ref[3][0][0][1] + 0.05                      # already at one of option 3's outputs
    for o in (2, 3, 4):
        got = np.asarray(pick(o, obs))
        for n, s in enumerate(obs):
            scores = [(0.0 if np.linalg.norm(s[:2] - s2) <= TOL else _value_np(s, s2)) + 0.95 * c
                      for _, s2, c in ref[o][0]]
            want = ref[o][0][int(np.argmax(scores))][1]
            np.testing.assert_allclose(got[n], want, rtol=1e-6, err_msg=f"o={o} n={n}")
    for o in (O.GLOBAL, O.GOAL):
        np.testing.assert_array_equal(pick(o, obs), np.broadcast_to(GOAL_XY, (20, 2)))


def _reacher_chain(n_angles=12):
    """Ant-Reacher-like chain around the goal (0, 0): each option's start states on a ring."""
    cfg = CFG.replace(max_pos_traj=n_angles, buffer_len=2)
    K, P, L = cfg.max_options, cfg.max_pos_traj, cfg.traj_len
    ang = 2 * np.pi * (np.arange(P) + 0.5) / P
    ring = np.stack([np.cos(ang), np.sin(ang)], -1)
    radius = {1: 2.0, 2: 5.0, 3: 8.0, 4: 11.0}
    pos_xy = np.zeros((K, P, L, 2), np.float32)
    for k, r in radius.items():
        pos_xy[k, :, 0] = r * ring
    pos_mask = np.zeros((K, P, L), bool)
    pos_mask[1:, :, 0] = True
    ch = O.chain_init(cfg, np.zeros(2, np.float32))
    return ch.replace(status=jnp.array([O.ALWAYS, O.MATURE, O.MATURE, O.MATURE, O.GESTATION]),
                      parent=jnp.array([-1, -1, 1, 2, 3]), num_options=jnp.asarray(5),
                      pos_xy=jnp.asarray(pos_xy), pos_mask=jnp.asarray(pos_mask),
                      pos_obs=jnp.asarray(pos_xy[:, :, 0]), pess_ok=jnp.asarray(pos_mask),
                      robust_ok=jnp.asarray(pos_mask))


def test_dp_subgoals_lie_between_agent_and_goal():
    """The paper's Figure 4: DP picks subgoals on the agent's side of the goal; robust sampling
    from the same chain often picks them on the far side."""
    ch = _reacher_chain()
    value = lambda s, g: -jnp.linalg.norm(s[:, :2] - g, axis=-1)
    table = jax.jit(S.dp_value_table, static_argnums=1)(ch, value)
    corners = np.array([[9, 9], [9, -9], [-9, 9], [-9, -9]], np.float32)
    overshoot = []
    for o in (3, 4):
        for a in corners:
            s = np.asarray(S.pick_subgoal(table, ch, o, a, value))
            cos = s @ a / (np.linalg.norm(s) * np.linalg.norm(a))
            assert cos > 0.95, (o, a, s)
            assert np.linalg.norm(a - s) + np.linalg.norm(s) <= np.linalg.norm(a) + 0.5
            xy, _ = robust_many(jax.random.split(jax.random.key(int(a[0] + 2 * a[1]) + o), 64), ch, o)
            xy = np.asarray(xy)
            overshoot.append(np.mean(xy @ a < 0))
    assert np.mean(overshoot) > 0.2, overshoot


def test_public_functions_jit_without_retracing(wide_chain):
    traces = {}

    def counted(name, f, **kw):
        def g(*a):
            traces[name] = traces.get(name, 0) + 1
            return f(*a)
        return jax.jit(g, **kw)

    value = lambda s, g: -jnp.linalg.norm(s[:, :2] - g, axis=-1)
    dp = counted("dp", lambda c: S.dp_value_table(c, value))
    pick = counted("pick", lambda t, c, o, x: jax.vmap(
        lambda a, b: S.pick_subgoal(t, c, a, b, value))(o, x))
    robust = counted("robust", lambda k, c, o: jax.vmap(
        lambda a, b: S.robust_subgoal(a, c, b))(k, o))
    chains = [wide_chain, _chain_with_link(spread=1.0, seed=5)]
    for n, ch in enumerate(chains):
        t = dp(ch)
        o = np.array([0, 1, 2], np.int32)
        xy = np.random.default_rng(n).normal(size=(3, 2)).astype(np.float32)
        pick(t, ch, o, xy)
        robust(jax.random.split(jax.random.key(n), 3), ch, o)
    assert traces == {"dp": 1, "pick": 1, "robust": 1}, traces
    init = S.dp_table_init(chains[0])
    assert jax.tree_util.tree_structure(init) == jax.tree_util.tree_structure(dp(chains[0]))

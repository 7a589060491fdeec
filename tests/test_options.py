"""The skill chain: state machine, batched recording, policy over options, chain probability."""
import numpy as np
import jax
import jax.numpy as jnp
import pytest

from dscpp_jax import options as O

GOAL_XY = np.array([0.0, 8.0], np.float32)
START_XY = np.array([0.0, 0.0], np.float32)
# one small config for the whole module (few compiled shapes -> fast tests)
CFG = O.ChainConfig(max_options=5, gestation=3, buffer_len=5, max_pos_traj=6, max_neg=4)

record = jax.jit(O.record_outcomes)
refit = jax.jit(O.refit)
grow = jax.jit(O.grow_chain)
select = jax.jit(O.select_option)
can_init = jax.jit(O.can_initiate)


def _traj(rng, center, spread, n, T):
    start = center + rng.uniform(-spread, spread, size=(n, 2))
    traj = center + rng.uniform(-spread, spread, size=(n, T, 2))
    return start.astype(np.float32), traj.astype(np.float32)


def _events(chain, option, center, n_success, n_fail=0, seed=0, spread=1.0, fail_center=START_XY):
    """Record n_success successes of `option` near `center` and n_fail failures started near
    `fail_center`, in one batch."""
    rng = np.random.default_rng(seed)
    n = n_success + n_fail
    B, T = 8, chain.cfg.buffer_len         # padded to one batch size: one compilation
    assert n <= B
    start, traj = _traj(rng, np.asarray(center, np.float32), spread, B, T)
    start[n_success:] = np.asarray(fail_center, np.float32) + rng.uniform(-0.5, 0.5, (B - n_success, 2))
    ids = np.full((B,), option, np.int32)
    succ = np.arange(B) < n_success
    ev = np.arange(B) < n
    return record(chain, ids, succ, start, traj, np.ones((B, T), bool), ev)


# ------------------------------------------------------------------------------------------------

def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="max_options"):
        O.ChainConfig(max_options=2)
    with pytest.raises(ValueError, match="variant"):
        O.ChainConfig(variant="triple")
    with pytest.raises(ValueError, match="gestation"):
        O.ChainConfig(gestation=0)
    with pytest.raises(ValueError, match="initiation_period"):
        O.ChainConfig(initiation_period=-1)
    with pytest.raises(ValueError, match="goal_xy"):
        O.chain_init(CFG, np.zeros(3))


def test_init_global_and_goal_option():
    ch = O.chain_init(CFG, GOAL_XY)
    np.testing.assert_array_equal(ch.status, [O.ALWAYS, O.GESTATION, O.FREE, O.FREE, O.FREE])
    assert int(ch.num_options) == 2
    np.testing.assert_array_equal(can_init(ch, START_XY), [True, True, False, False, False])
    # the goal option (in gestation) initiates everywhere, except where it is already done
    assert int(select(ch, START_XY)) == O.GOAL
    assert int(select(ch, GOAL_XY + 0.1)) == O.GLOBAL
    assert bool(O.option_terminates(ch, O.GOAL, GOAL_XY + np.array([0.5, 0.0])))
    assert not bool(O.option_terminates(ch, O.GOAL, GOAL_XY + np.array([0.0, 0.7])))
    assert bool(O.option_terminates(ch, O.GLOBAL, GOAL_XY))


# ------------------------------------------------------------------------------------------------
# record_outcomes: batched == one by one

def _ref_record(ref, status, ids, succ, start, traj, tmask, ev, start_obs):
    K, P, L = ref["pos_xy"].shape[:3]
    N = ref["neg_xy"].shape[1]
    for b in range(len(ids)):
        o = int(ids[b])
        if not ev[b] or o < 0 or o >= K or status[o] == O.FREE:
            continue
        ref["executions"][o] += 1
        if succ[b]:
            ref["successes"][o] += 1
        if o == O.GLOBAL:
            continue
        ref["dirty"][o] = True
        if succ[b]:
            s = ref["pos_count"][o] % P
            ref["pos_xy"][o, s, 0] = start[b]
            ref["pos_xy"][o, s, 1:] = traj[b]
            ref["pos_mask"][o, s, 0] = True
            ref["pos_mask"][o, s, 1:] = tmask[b]
            ref["pos_obs"][o, s] = start_obs[b]
            ref["pos_count"][o] += 1
        else:
            s = ref["neg_count"][o] % N
            ref["neg_xy"][o, s] = start[b]
            ref["neg_mask"][o, s] = True
            ref["neg_count"][o] += 1


def test_record_outcomes_batched_equals_sequential():
    cfg = CFG.replace(obs_dim=3, max_pos_traj=3, max_neg=2)  # small rings: bursts overflow them
    ch = O.chain_init(cfg, GOAL_XY)
    status = np.array([O.ALWAYS, O.MATURE, O.MATURE, O.GESTATION, O.FREE], np.int32)
    ch = ch.replace(status=jnp.asarray(status))
    names = ["pos_xy", "pos_mask", "pos_obs", "pos_count", "neg_xy", "neg_mask", "neg_count",
             "executions", "successes", "dirty"]
    ref = {k: np.array(getattr(ch, k)) for k in names}
    rng = np.random.default_rng(1)
    B, T = 16, cfg.buffer_len
    rec = jax.jit(O.record_outcomes)
    for step in range(6):
        ids = rng.integers(-1, cfg.max_options + 1, size=B).astype(np.int32)
        if step == 2:
            ids[:] = 2  # every env ends the same option at once (more than the ring holds)
        succ = rng.random(B) < 0.6
        ev = rng.random(B) < 0.8
        start = rng.normal(size=(B, 2)).astype(np.float32)
        traj = rng.normal(size=(B, T, 2)).astype(np.float32)
        tmask = rng.random((B, T)) < 0.7
        obs = rng.normal(size=(B, 3)).astype(np.float32)
        ch = rec(ch, ids, succ, start, traj, tmask, ev, obs)
        _ref_record(ref, status, ids, succ, start, traj, tmask, ev, obs)
        for k in names:
            np.testing.assert_array_equal(np.asarray(getattr(ch, k)), ref[k], err_msg=f"{k} step {step}")
    assert ref["pos_count"][2] > cfg.max_pos_traj  # the rings did wrap


def test_ring_slots_never_collide():
    """Kept writes of one batch hit distinct (row, slot) pairs, the last `capacity` events of each
    row survive, and slots continue the ring: sequential semantics without relying on the order
    in which a scatter applies duplicate indices."""
    rng = np.random.default_rng(3)
    K, cap = 5, 3
    for _ in range(20):
        B = 12
        oid = rng.integers(0, K, B)
        ev = rng.random(B) < 0.7
        count = rng.integers(0, 10, K)
        row, slot, n_new = O._ring_slots(jnp.asarray(oid), jnp.asarray(ev), jnp.asarray(count), cap)
        row, slot = np.asarray(row), np.asarray(slot)
        kept = row < K
        pairs = list(zip(row[kept], slot[kept]))
        assert len(pairs) == len(set(pairs))
        for k in range(K):
            idx = np.flatnonzero(ev & (oid == k))
            assert int(n_new[k]) == len(idx)
            np.testing.assert_array_equal(np.flatnonzero(kept & (row == k)), idx[-cap:])
            np.testing.assert_array_equal(slot[idx[-cap:]],
                                          (count[k] + np.arange(len(idx))[-cap:]) % cap)


def test_record_outcomes_checks_shapes():
    ch = O.chain_init(CFG, GOAL_XY)
    B, T = 2, CFG.buffer_len
    with pytest.raises(ValueError, match="traj_xy"):
        O.record_outcomes(ch, np.ones(B, np.int32), np.ones(B, bool), np.zeros((B, 2)),
                          np.zeros((B, T + 1, 2)), np.ones((B, T), bool), np.ones(B, bool))
    with pytest.raises(ValueError, match="start_obs"):
        O.record_outcomes(O.chain_init(CFG.replace(obs_dim=4), GOAL_XY), np.ones(B, np.int32),
                          np.ones(B, bool), np.zeros((B, 2)), np.zeros((B, T, 2)),
                          np.ones((B, T), bool), np.ones(B, bool))


def test_ring_to_chronological():
    ring = np.arange(10, dtype=np.float32).reshape(5, 2)      # positions 0..4 written, head = 2
    xy, m = O.ring_to_chronological(jnp.asarray(ring), 2, 7)
    np.testing.assert_array_equal(xy[:, 0], ring[[2, 3, 4, 0, 1], 0])
    assert bool(m.all())
    xy, m = O.ring_to_chronological(jnp.asarray(ring), 3, 3)   # only slots 0, 1, 2 written
    np.testing.assert_array_equal(xy[m][:, 0], ring[[0, 1, 2], 0])


def test_refit_fits_dirty_rows_on_their_examples():
    """refit hands each dirty row its own positives (start + trajectory) and negatives:
    the result decides like scikit-learn's SVC -> OneClassSVM pipeline on the same examples."""
    from dscpp_jax import initiation as I
    from sklearn.svm import SVC, OneClassSVM

    ch = O.chain_init(CFG, GOAL_XY)
    ch = ch.replace(status=jnp.array([O.ALWAYS, O.MATURE, O.GESTATION, O.FREE, O.FREE]),
                    parent=jnp.array([-1, -1, 1, -1, -1]), num_options=jnp.asarray(3))
    ch = _events(ch, 1, (0.0, 7.0), 5, n_fail=3, seed=7, fail_center=(2.0, 5.0))
    ch = _events(ch, 0, (0.0, 0.0), 2, n_fail=2, seed=9)     # the global option: counters only
    np.testing.assert_array_equal(ch.dirty, [False, True, False, False, False])
    assert int(ch.executions[0]) == 4 and int(ch.pos_count[0]) == int(ch.neg_count[0]) == 0
    out = refit(ch)
    np.testing.assert_array_equal(out.fitted, [False, True, False, False, False])
    assert not bool(out.dirty.any())
    pos = np.asarray(ch.pos_xy[1])[np.asarray(ch.pos_mask[1])]
    neg = np.asarray(ch.neg_xy[1])[np.asarray(ch.neg_mask[1])]
    assert len(pos) > 5 * CFG.buffer_len and len(neg) == 3
    X = np.concatenate([pos, neg])
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    svc = SVC(kernel="rbf", gamma=0.5, C=1.0).fit(X, y)
    occ = OneClassSVM(kernel="rbf", gamma=0.5, nu=0.1).fit(pos[svc.predict(pos) == 1])
    grid = np.stack(np.meshgrid(np.linspace(-4, 6, 31), np.linspace(0, 12, 31)), -1)
    grid = grid.reshape(-1, 2).astype(np.float32)
    row = _row(out, 1)
    f_opt = svc.decision_function(grid)
    f_pes = occ.decision_function(grid)
    got_opt = np.asarray(I.optimistic_contains(row, grid))
    got_pes = np.asarray(I.pessimistic_contains(row, grid))
    sure_opt = np.abs(f_opt) > 1e-2
    sure_pes = np.abs(f_pes) > 1e-2 * np.abs(f_pes).max()
    np.testing.assert_array_equal(got_opt[sure_opt], f_opt[sure_opt] >= 0)
    np.testing.assert_array_equal(got_pes[sure_pes], f_pes[sure_pes] > 0)
    assert got_pes.any() and not got_pes.all() and not got_opt.all()


# ------------------------------------------------------------------------------------------------
# the chain state machine, driven by scripted outcomes (real classifiers)

# where each option succeeds from. Successes only: a two-class SVC fitted on a handful of
# negatives is positive far from all data, which would make coverage a matter of luck here
# (negatives are checked by the batched-recording and refit tests).
REGIONS = {1: (0.0, 7.0), 2: (0.0, 4.0), 3: (0.0, 0.5)}


def _grow_script():
    """Goal option, then links 2 and 3, each mature after `gestation` scripted successes; link 3's
    successes cover the start state. Returns the chain after every stage."""
    stages = {}
    ch = O.chain_init(CFG, GOAL_XY)
    g = CFG.gestation
    # the goal option: successes near the goal
    ch = _events(ch, 1, REGIONS[1], g - 1, seed=1)
    ch = grow(ch, START_XY)
    stages["goal_gestating"] = ch
    ch = _events(ch, 1, REGIONS[1], 1, seed=2)
    ch = grow(ch, START_XY)                  # mature, but never fitted: no new option yet
    stages["goal_matured_unfitted"] = ch
    ch = grow(refit(ch), START_XY)
    stages["link2_created"] = ch
    ch = _events(ch, 2, REGIONS[2], g - 1, seed=3)
    ch = grow(refit(ch), START_XY)
    stages["link2_gestating"] = ch
    ch = _events(ch, 2, REGIONS[2], 2, seed=4)
    ch = grow(refit(ch), START_XY)
    stages["link3_created"] = ch
    ch = _events(ch, 3, REGIONS[3], g, seed=5)
    ch = grow(refit(ch), START_XY)
    stages["covered"] = ch
    stages["covered_again"] = grow(refit(ch), START_XY)
    return stages


@pytest.fixture(scope="module")
def grown_chain():
    return _grow_script()


def _row(ch, k):
    return jax.tree_util.tree_map(lambda a: a[k], ch.clf)


def _uncovered_point(ch):
    """A point of a grid that no mature option's initiation set holds (checked directly)."""
    from dscpp_jax import initiation as I

    mature = [k for k in range(CFG.max_options) if int(ch.status[k]) == O.MATURE]
    grid = [np.array([x, y]) for x in np.linspace(-20, 20, 9) for y in np.linspace(-20, 20, 9)]
    for xy in grid:
        xy = xy.astype(np.float32)
        if not any(bool(I.initiation_contains(_row(ch, k), xy)) for k in mature):
            return xy
    raise AssertionError("every grid point is covered by some mature option")


def test_gestation_maturity_growth(grown_chain):
    s = grown_chain
    F, G, M, A = O.FREE, O.GESTATION, O.MATURE, O.ALWAYS
    g = CFG.gestation
    np.testing.assert_array_equal(s["goal_gestating"].status, [A, G, F, F, F])
    assert int(s["goal_gestating"].num_options) == 2
    # mature once it has `gestation` successes, but no new option before its classifiers are fit
    np.testing.assert_array_equal(s["goal_matured_unfitted"].status, [A, M, F, F, F])
    assert int(s["goal_matured_unfitted"].num_options) == 2
    ch = s["link2_created"]
    np.testing.assert_array_equal(ch.status, [A, M, G, F, F])
    np.testing.assert_array_equal(ch.parent[:3], [-1, -1, 1])
    assert int(ch.num_options) == 3
    # one option in gestation at a time
    np.testing.assert_array_equal(s["link2_gestating"].status, [A, M, G, F, F])
    ch = s["link3_created"]
    np.testing.assert_array_equal(ch.status, [A, M, M, G, F])
    np.testing.assert_array_equal(ch.parent[:4], [-1, -1, 1, 2])
    np.testing.assert_array_equal(ch.successes, [0, g, g + 1, 0, 0])
    np.testing.assert_array_equal(ch.executions, [0, g, g + 1, 0, 0])
    # link 3 covers the start: the chain stops growing, and stays stopped
    for key in ("covered", "covered_again"):
        ch = s[key]
        np.testing.assert_array_equal(ch.status, [A, M, M, M, F])
        assert int(ch.num_options) == 4 and not bool(ch.capacity_hit)
        assert bool(O.start_covered(ch, START_XY))
        assert not bool(ch.dirty.any()) and bool(ch.fitted[1:4].all())


def test_metrics_follow_the_option_in_gestation(grown_chain):
    s, g = grown_chain, CFG.gestation
    metrics = jax.jit(O.chain_metrics)
    gest = metrics(s["link2_gestating"], START_XY)   # link 2: g - 1 successful executions so far
    assert int(gest["num_gestation"]) == 1 and int(gest["num_mature"]) == 1
    assert int(gest["gestation_executions"]) == int(gest["gestation_successes"]) == g - 1
    assert int(gest["gestation_parent"]) == 1                  # link 2 targets the goal option
    fresh = metrics(s["link3_created"], START_XY)     # link 3 just created: never tried yet
    assert int(fresh["gestation_executions"]) == int(fresh["gestation_successes"]) == 0
    assert int(fresh["gestation_parent"]) == 2
    done = metrics(s["covered"], START_XY)            # nothing in gestation
    assert int(done["num_gestation"]) == int(done["gestation_executions"]) == 0
    assert int(done["gestation_parent"]) == -1


def _nearest_mean_np(starts, target):
    """Plain NumPy oracle: mean over starts of the distance to the nearest target point."""
    if len(starts) == 0 or len(target) == 0:
        return float("nan")
    return float(np.mean([min(np.hypot(*(s - t)) for t in target) for s in starts]))


def test_gestation_start_distances_against_numpy(grown_chain):
    """The option in gestation: mean distance of its stored failed and successful starts to its
    target's nearest positive state (the task goal for the goal option); NaN where none."""
    s = grown_chain
    dist = jax.jit(O.gestation_start_distances)
    # link 2 in gestation (targets the goal option), with two failures from near the start
    ch = _events(s["link2_gestating"], 2, REGIONS[2], 0, n_fail=2, seed=7)
    got_fail, got_succ = (float(v) for v in dist(ch))
    pos_xy, pos_mask = np.asarray(ch.pos_xy), np.asarray(ch.pos_mask)
    target = pos_xy[1][pos_mask[1]]                                    # the goal option's states
    fails = np.asarray(ch.neg_xy)[2][np.asarray(ch.neg_mask)[2]]
    succ = pos_xy[2, :, 0][pos_mask[2, :, 0]]
    assert len(fails) == 2 and len(succ) == CFG.gestation - 1 and len(target) > 0
    np.testing.assert_allclose(got_fail, _nearest_mean_np(fails, target), rtol=1e-5)
    np.testing.assert_allclose(got_succ, _nearest_mean_np(succ, target), rtol=1e-5)
    assert got_fail > got_succ          # failures started near the start, successes near (0, 4)
    # the goal option in gestation: distances to the task goal; no failures yet -> NaN
    goal_fail, goal_succ = (float(v) for v in dist(s["goal_gestating"]))
    g0 = s["goal_gestating"]
    succ0 = np.asarray(g0.pos_xy)[1, :, 0][np.asarray(g0.pos_mask)[1, :, 0]]
    assert np.isnan(goal_fail)
    np.testing.assert_allclose(goal_succ, _nearest_mean_np(succ0, GOAL_XY[None]), rtol=1e-5)
    # nothing in gestation: NaN, and chain_metrics carries both
    m = jax.jit(O.chain_metrics)(s["covered"], START_XY)
    assert np.isnan(float(m["gestation_fail_distance"])) and np.isnan(float(m["gestation_success_distance"]))
    m = jax.jit(O.chain_metrics)(ch, START_XY)
    np.testing.assert_allclose(float(m["gestation_fail_distance"]), got_fail, rtol=1e-6)


def test_unbounded_regions_counts_mature_options_whose_region_has_no_bound(grown_chain):
    """An optimistic SVC whose intercept is above zero holds every point far from its examples
    (a fit that happens: successes spread out, failures clustered among them, as scikit-learn
    fits it too); `unbounded_regions` counts such mature options, and only those."""
    from dscpp_jax import initiation as I
    rng = np.random.default_rng(0)
    pos = rng.uniform(-5, 5, (60, 2)).astype(np.float32)
    neg = rng.normal(0, 0.7, (40, 2)).astype(np.float32)
    clf = I.fit_initiation(jnp.asarray(pos), jnp.ones(60, bool), jnp.asarray(neg), jnp.ones(40, bool))
    far = jnp.asarray(O.UNBOUNDED_PROBE_XY, jnp.float32)
    assert float(clf.optimistic.rho) < 0
    assert bool(I.initiation_contains(clf, far)) and bool(I.initiation_contains(clf, jnp.array([60.0, -45.0])))
    assert not bool(I.initiation_contains(clf, jnp.zeros(2)))      # the failures' neighbourhood
    sk = pytest.importorskip("sklearn.svm").SVC(C=1.0, gamma=0.5, class_weight="balanced").fit(
        np.concatenate([pos, neg]), np.r_[np.ones(60), -np.ones(40)])
    assert sk.decision_function([[60.0, -45.0]])[0] > 0

    metrics = jax.jit(O.chain_metrics)
    ch = grown_chain["covered"]                                    # rows 1-3 mature, bounded
    assert int(metrics(ch, START_XY)["unbounded_regions"]) == 0
    for row, want in ((2, 1), (4, 0)):                             # row 4 is free: not counted
        rho = ch.clf.optimistic.rho.at[row].set(-1.0)
        bad = ch.replace(clf=ch.clf.replace(optimistic=ch.clf.optimistic.replace(rho=rho)))
        assert int(metrics(bad, START_XY)["unbounded_regions"]) == want


def test_growth_uses_the_given_start(grown_chain):
    ch = grown_chain["covered"]
    far = _uncovered_point(ch)
    assert not bool(O.start_covered(ch, far))
    grown = grow(ch, far)
    assert int(grown.num_options) == 5 and int(grown.status[4]) == O.GESTATION
    assert int(grown.parent[4]) == 3


def test_initiation_period_delays_the_child():
    """Baseline DSC's rule (DSC 2020 `OptionClass.get_training_phase`; the model-free baseline's
    `should_create_new_option` waits for "initiation_done"): the child of the newest mature
    option is created once that option has gestation + initiation_period successes, not at
    maturity; 0 creates it at maturity."""
    period, g = 2, CFG.gestation
    cfg = CFG.replace(initiation_period=period)
    grow_p = jax.jit(O.grow_chain)
    seen = []
    for c in (cfg, CFG):
        ch = _events(O.chain_init(c, GOAL_XY), 1, GOAL_XY, g, n_fail=2, seed=3)
        ch = grow_p(refit(ch), START_XY)
        steps = [(int(ch.status[1]), int(ch.num_options))]
        for k in range(period):
            ch = _events(ch, 1, GOAL_XY, 1, seed=4 + k)
            ch = grow_p(refit(ch), START_XY)
            steps.append((int(ch.status[1]), int(ch.num_options)))
        seen.append(steps)
    # with the period: mature at g successes, the child at g + period
    assert seen[0] == [(O.MATURE, 2), (O.MATURE, 2), (O.MATURE, 3)]
    # without: the child at maturity
    assert seen[1] == [(O.MATURE, 3)] * (period + 1)


def test_capacity_is_reported():
    ch = O.chain_init(CFG, GOAL_XY)
    g = CFG.gestation
    for o in range(1, CFG.max_options):      # successes nowhere near the start: never covered
        ch = _events(ch, o, (3.0 * o, 20.0), g, seed=o)
        ch = grow(refit(ch), START_XY)
        assert int(ch.num_options) == min(o + 2, CFG.max_options)
        assert bool(ch.capacity_hit) == (o == CFG.max_options - 1)
    np.testing.assert_array_equal(ch.status, [O.ALWAYS] + [O.MATURE] * (CFG.max_options - 1))
    np.testing.assert_array_equal(ch.parent, [-1, -1, 1, 2, 3])
    assert int(jax.jit(O.chain_metrics)(ch, START_XY)["capacity_hit"]) == 1


def _ref_select(ch, xy):
    """The walk from the goal option outward, using the classifiers directly."""
    from dscpp_jax import initiation as I

    row = lambda k: _row(ch, k)
    xy = jnp.asarray(xy, jnp.float32)
    for k in range(1, int(ch.num_options)):
        st = int(ch.status[k])
        init = st == O.GESTATION or (st == O.MATURE and bool(I.initiation_contains(row(k), xy)))
        if k == O.GOAL:
            done = np.linalg.norm(np.asarray(xy) - GOAL_XY) <= CFG.goal_tolerance
        else:
            done = bool(I.pessimistic_contains(row(int(ch.parent[k])), xy))
        if init and not done:
            return k
    return O.GLOBAL


def test_policy_over_options(grown_chain):
    ch = grown_chain["covered"]
    assert int(select(ch, START_XY)) == 3
    assert int(select(ch, np.array([0.0, 7.0], np.float32))) == 1
    assert int(select(ch, np.array([0.0, 7.9], np.float32))) == 0      # at the goal already
    assert int(select(ch, _uncovered_point(ch))) == 0                  # nobody's region
    xs = np.linspace(-3, 3, 7)
    ys = np.linspace(-2, 10, 13)
    for x in xs:
        for y in ys:
            xy = np.array([x, y], np.float32)
            assert int(select(ch, xy)) == _ref_select(ch, xy), xy
    # an explicit "already done" mask overrides the termination test
    at = np.array([False, False, False, True, False])
    assert int(select(ch, START_XY, at)) != 3
    # while link 3 gestates it initiates anywhere the earlier options do not
    ch3 = grown_chain["link3_created"]
    assert int(select(ch3, _uncovered_point(ch3))) == 3


def _ref_select_pessimistic_first(ch, xy):
    from dscpp_jax import initiation as I

    xy = jnp.asarray(xy, jnp.float32)
    for k in range(1, int(ch.num_options)):
        if int(ch.status[k]) != O.MATURE or not bool(I.pessimistic_contains(_row(ch, k), xy)):
            continue
        if k == O.GOAL:
            done = np.linalg.norm(np.asarray(xy) - GOAL_XY) <= CFG.goal_tolerance
        else:
            done = bool(I.pessimistic_contains(_row(ch, int(ch.parent[k])), xy))
        if not done:
            return k
    return _ref_select(ch, xy)


def test_policy_over_options_pessimistic_first(grown_chain):
    # a few failures of link 2 far from the start turn its optimistic region into a two-class SVC
    # that is positive far from all data, the start included: the paper's walk then picks link 2
    # at the start, the pessimistic-first walk keeps link 3, whose pessimistic region holds it
    ch = _events(grown_chain["covered"], 2, REGIONS[2], 0, n_fail=3, seed=9,
                 fail_center=np.array([6.0, 4.0], np.float32))
    ch = refit(ch)
    sel = jax.jit(lambda c, p: O.select_option(c, p, prefer_pessimistic=True))
    assert int(select(ch, START_XY)) == 2 and int(sel(ch, START_XY)) == 3
    for x in np.linspace(-3, 3, 7):
        for y in np.linspace(-2, 10, 25):
            xy = np.array([x, y], np.float32)
            assert int(sel(ch, xy)) == _ref_select_pessimistic_first(ch, xy), xy
            assert int(select(ch, xy)) == _ref_select(ch, xy), xy


def test_termination_and_local_success(grown_chain):
    from dscpp_jax import initiation as I

    ch = grown_chain["covered"]
    row1 = jax.tree_util.tree_map(lambda a: a[1], ch.clf)
    for xy in ([0.0, 7.0], [0.0, 4.0], [0.0, 0.0], [5.0, 5.0]):
        xy = np.array(xy, np.float32)
        assert bool(O.option_terminates(ch, 2, xy)) == bool(I.pessimistic_contains(row1, xy))
    inside = np.array([0.0, 7.0], np.float32)
    assert bool(O.option_terminates(ch, 2, inside))
    assert bool(O.local_success(ch, 2, inside, inside + 0.3))
    assert not bool(O.local_success(ch, 2, inside, inside + 1.0))
    assert not bool(O.local_success(ch, 2, np.array([9.0, 0.0], np.float32),
                                    np.array([9.0, 0.0], np.float32)))
    term = O.in_termination_region(ch, inside)
    for k in range(4):
        assert bool(term[k]) == bool(O.option_terminates(ch, k, inside))


def test_chain_probability_and_rates():
    ch = O.chain_init(CFG, GOAL_XY)
    ch = ch.replace(status=jnp.array([O.ALWAYS, O.MATURE, O.MATURE, O.GESTATION, O.FREE]),
                    successes=jnp.array([5, 8, 3, 1, 7]), executions=jnp.array([9, 10, 6, 4, 9]))
    np.testing.assert_allclose(O.success_rates(ch), [5 / 9, 0.8, 0.5, 0.25, 7 / 9], rtol=1e-6)
    np.testing.assert_allclose(O.chain_probability(ch), 0.8 * 0.5 * 0.25, rtol=1e-6)
    ch = ch.replace(executions=jnp.array([9, 10, 6, 0, 9]), successes=jnp.array([5, 8, 3, 0, 7]))
    assert float(O.chain_probability(ch)) == 0.0     # an option never executed


def test_public_functions_jit_without_retracing(grown_chain):
    traces = {}

    def counted(name, f):
        def g(*a):
            traces[name] = traces.get(name, 0) + 1
            return f(*a)
        return jax.jit(g)

    fns = {
        "terminates": counted("terminates", lambda c, o, x: jax.vmap(
            lambda a, b: O.option_terminates(c, a, b))(o, x)),
        "local_success": counted("local_success", lambda c, o, x: jax.vmap(
            lambda a, b: O.local_success(c, a, b, b))(o, x)),
        "metrics": counted("metrics", O.chain_metrics),
        "probability": counted("probability", O.chain_probability),
    }
    module_jits = {"refit": refit, "grow": grow, "select": select, "can_init": can_init,
                   "record": record}
    module_jits = {k: f for k, f in module_jits.items() if hasattr(f, "_cache_size")}
    sizes = None
    for n, key in enumerate(("link2_gestating", "covered", "link3_created")):
        ch = grown_chain[key]
        xy = np.random.default_rng(n).normal(size=(3, 2)).astype(np.float32)
        o = np.array([1, 2, 3], np.int32)
        fns["terminates"](ch, o, xy)
        fns["local_success"](ch, o, xy)
        fns["metrics"](ch, START_XY)
        fns["probability"](ch)
        can_init(ch, xy[0])
        select(ch, xy[n])
        grow(ch, xy[n])
        refit(ch)
        _events(ch, n + 1, xy[n], n + 1, seed=n)
        if sizes is None:   # (the module-level jits may have compiled earlier: count from here)
            sizes = {k: f._cache_size() for k, f in module_jits.items()}
    assert traces == {k: 1 for k in fns}, traces
    assert {k: f._cache_size() for k, f in module_jits.items()} == sizes


def test_single_classifier_variant():
    """Baseline DSC: one classifier per option, both the initiation set and the child's target."""
    from dscpp_jax import initiation as I

    cfg = CFG.replace(variant="single")
    icfg = O.initiation_config(cfg)
    assert icfg.variant == "single" and icfg.gamma == cfg.svm_gamma
    ch = O.chain_init(cfg, GOAL_XY)
    ch = _events(ch, 1, (0.0, 7.0), cfg.gestation, seed=11)
    ch = jax.jit(O.grow_chain)(jax.jit(O.refit)(ch), START_XY)
    assert int(ch.num_options) == 3
    row = _row(ch, 1)
    grid = np.stack(np.meshgrid(np.linspace(-4, 4, 9), np.linspace(3, 11, 9)), -1).reshape(-1, 2)
    grid = grid.astype(np.float32)
    pes = np.asarray(I.pessimistic_contains(row, grid))
    assert pes.any() and not pes.all()
    np.testing.assert_array_equal(np.asarray(I.initiation_contains(row, grid)), pes)
    for xy in grid[::7]:
        assert bool(O.can_initiate(ch, xy)[1]) == bool(I.pessimistic_contains(row, xy))
        assert bool(O.option_terminates(ch, 2, xy)) == bool(I.pessimistic_contains(row, xy))

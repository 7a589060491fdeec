"""Ring replay invariants and HER relabelling against a plain NumPy model of the write history."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax.her import her_index, her_relabel, her_sample, segment_last_offset
from dscpp_jax.replay import (TrajStep, replay_add, replay_add_many, replay_flatten, replay_init,
                              replay_sample, replay_sample_index, replay_size, valid_positions)

OBS, ACT, GOAL = 4, 2, 2


def _example():
    return TrajStep(obs=jnp.zeros(OBS), action=jnp.zeros(ACT), next_obs=jnp.zeros(OBS),
                    goal=jnp.zeros(GOAL), seg_id=jnp.zeros((), jnp.int32))


def _history(rng, steps, num_envs, p_new_seg=0.15, p_invalid=0.1):
    """Random time-major trajectories: per env, segments of random length, a few invalid steps.

    Positions are small integers so that goals are hit exactly now and then.
    """
    seg = np.zeros(num_envs, np.int32)
    hist = []
    for _ in range(steps):
        seg = seg + (rng.random(num_envs) < p_new_seg)
        hist.append(dict(
            obs=rng.integers(-2, 3, (num_envs, OBS)).astype(np.float32),
            action=rng.uniform(-1, 1, (num_envs, ACT)).astype(np.float32),
            next_obs=rng.integers(-2, 3, (num_envs, OBS)).astype(np.float32),
            goal=rng.integers(-2, 3, (num_envs, GOAL)).astype(np.float32),
            seg_id=seg.copy(),
            valid=rng.random(num_envs) >= p_invalid,
        ))
    return hist


def _fill(hist, capacity, num_envs):
    buf = replay_init(_example(), capacity, num_envs)
    add = jax.jit(replay_add)
    for h in hist:
        item = TrajStep(*(jnp.asarray(h[k]) for k in ("obs", "action", "next_obs", "goal", "seg_id")))
        buf = add(buf, item, jnp.asarray(h["valid"]))
    return buf


# ---------------------------------------------------------------------------------------------
# ring buffer
def test_ring_layout_matches_numpy_model():
    rng = np.random.default_rng(0)
    num_envs, capacity, steps = 3, 23, 17  # rows = 7, wraps twice
    hist = _history(rng, steps, num_envs)
    buf = _fill(hist, capacity, num_envs)
    rows = capacity // num_envs
    assert buf.rows == rows and buf.capacity == rows * num_envs
    assert int(buf.ptr) == steps % rows and int(buf.rows_written) == steps
    for r in range(rows):
        t = max(t for t in range(steps) if t % rows == r)  # newest write of this row
        np.testing.assert_array_equal(np.asarray(buf.data.obs[r]), hist[t]["obs"])
        np.testing.assert_array_equal(np.asarray(buf.data.seg_id[r]), hist[t]["seg_id"])
        np.testing.assert_array_equal(np.asarray(buf.valid[r]), hist[t]["valid"])
    assert int(replay_size(buf)) == int(np.asarray(buf.valid).sum())


def test_partially_filled_buffer_has_invalid_tail_and_zero_storage():
    buf = replay_init(_example(), 100, 4)
    buf = replay_add(buf, TrajStep(jnp.ones((4, OBS)), jnp.ones((4, ACT)), jnp.ones((4, OBS)),
                                   jnp.ones((4, GOAL)), jnp.ones(4, jnp.int32)))
    assert int(replay_size(buf)) == 4
    assert not np.asarray(buf.valid[1:]).any()
    assert float(jnp.abs(buf.data.obs[1:]).sum()) == 0.0


def test_add_many_equals_repeated_add():
    rng = np.random.default_rng(1)
    hist = _history(rng, 11, 2)
    ref = _fill(hist, 16, 2)  # rows = 8: the chunk wraps
    stack = lambda k: jnp.asarray(np.stack([h[k] for h in hist]))
    keys = ("obs", "action", "next_obs", "goal", "seg_id")
    many = replay_init(_example(), 16, 2)
    for t in range(4):
        many = replay_add(many, TrajStep(*(stack(k)[t] for k in keys)), stack("valid")[t])
    rest = TrajStep(*(stack(k)[4:] for k in keys))  # 7 slices from row 4: wraps to row 2
    many = jax.jit(replay_add_many)(many, rest, stack("valid")[4:])
    for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(many)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_sampling_is_uniform_over_valid_entries_only():
    buf = replay_init(jnp.zeros(()), 40, 4)  # generic leaf: a scalar tag per item
    rng = np.random.default_rng(2)
    for t in range(10):
        tags = jnp.asarray(np.arange(4) + 4 * t, jnp.float32)
        buf = replay_add(buf, tags, jnp.asarray(rng.random(4) < 0.5))
    valid_tags = set(np.asarray(buf.data)[np.asarray(buf.valid)].tolist())
    samples = np.asarray(jax.jit(replay_sample, static_argnums=2)(buf, jax.random.key(0), 20000))
    assert set(samples.tolist()) == valid_tags  # every valid entry is reachable, no invalid one
    counts = np.array([np.sum(samples == v) for v in sorted(valid_tags)])
    expected = 20000 / len(valid_tags)
    chi2 = np.sum((counts - expected) ** 2 / expected)
    assert chi2 < 3 * len(valid_tags) + 30, (chi2, counts)


def test_flat_fifo_for_model_transitions():
    """A ring of (obs, action, next_obs) tuples used as a FIFO: old items are overwritten first."""
    ex = (jnp.zeros(3), jnp.zeros(1), jnp.zeros(3))
    buf = replay_init(ex, 6, 2)
    for t in range(5):
        v = jnp.full((2, 1), t, jnp.float32)
        buf = replay_add(buf, (jnp.repeat(v, 3, 1), v, jnp.repeat(v, 3, 1) + 1))
    items, mask = replay_flatten(buf)
    assert items[1].shape == (6, 1) and mask.shape == (6,)
    assert sorted(np.asarray(items[1])[np.asarray(mask), 0].tolist()) == [2, 2, 3, 3, 4, 4]
    obs, act, nxt = replay_sample(buf, jax.random.key(1), 64)
    np.testing.assert_allclose(np.asarray(nxt), np.asarray(obs) + 1)
    assert set(np.asarray(act)[:, 0].tolist()) <= {2.0, 3.0, 4.0}


def test_bad_input_raises_clear_errors():
    with pytest.raises(ValueError, match="capacity"):
        replay_init(_example(), 2, 4)
    buf = replay_init(_example(), 16, 4)
    bad = TrajStep(jnp.zeros((3, OBS)), jnp.zeros((3, ACT)), jnp.zeros((3, OBS)), jnp.zeros((3, GOAL)),
                   jnp.zeros(3, jnp.int32))
    with pytest.raises(ValueError, match="num_envs=4"):
        replay_add(buf, bad)
    with pytest.raises(ValueError, match="strategy"):
        her_sample(jax.random.key(0), buf, 8, strategy="episode")


# ---------------------------------------------------------------------------------------------
# HER
def _her_reference(hist, rows, sampled, u_future, u_relabel, strategy, relabel_prob, max_segment,
                   tol=0.6):
    """Plain NumPy HER over the *write history* (not the ring): walk forward in time."""
    steps = len(hist)
    out = {k: [] for k in ("goal", "reward", "discount", "obs", "next_obs")}
    for (r, e), uf, ur in zip(sampled, u_future, u_relabel):
        t = max(t for t in range(steps) if t % rows == r)
        h = hist[t]
        assert h["valid"][e]
        last = 0
        while (t + last + 1 < steps and last + 1 < max_segment
               and hist[t + last + 1]["valid"][e]
               and hist[t + last + 1]["seg_id"][e] == h["seg_id"][e]):
            last += 1
        goal = h["goal"][e]
        if strategy != "none":
            k = last if strategy == "final" else min(int(np.floor(uf * (last + 1))), last)
            if ur < relabel_prob:
                goal = hist[t + k]["next_obs"][e][:2]
        reached = np.linalg.norm(h["next_obs"][e][:2] - goal) <= tol
        out["goal"].append(goal)
        out["reward"].append(0.0 if reached else -1.0)
        out["discount"].append(0.0 if reached else 1.0)
        out["obs"].append(h["obs"][e])
        out["next_obs"].append(h["next_obs"][e])
    return {k: np.asarray(v, np.float32) for k, v in out.items()}


@pytest.mark.parametrize("strategy", ["final", "future", "none"])
@pytest.mark.parametrize("steps,max_segment", [(9, 200), (61, 200), (61, 4)])
def test_her_matches_numpy_reference(strategy, steps, max_segment):
    """Covers a partly filled ring, wrap-around (61 writes into 20 rows), segments still running at
    the newest row, segments cut by invalid steps, and the max_segment window."""
    rng = np.random.default_rng(steps + max_segment)
    num_envs, capacity = 3, 60
    hist = _history(rng, steps, num_envs)
    buf = _fill(hist, capacity, num_envs)
    rows = capacity // num_envs
    valid = np.argwhere(np.asarray(buf.valid))
    sampled = valid[rng.integers(0, len(valid), 300)]
    u_future = rng.random(300).astype(np.float32)
    u_relabel = rng.random(300).astype(np.float32)
    relabel = jax.jit(her_relabel, static_argnames=("strategy", "max_segment"))
    got = relabel(buf, jnp.asarray(sampled[:, 0], jnp.int32), jnp.asarray(sampled[:, 1], jnp.int32),
                  jnp.asarray(u_future), jnp.asarray(u_relabel), strategy=strategy,
                  relabel_prob=0.5, max_segment=max_segment, goal_tolerance=0.6)
    ref = _her_reference(hist, rows, sampled, u_future, u_relabel, strategy, 0.5, max_segment)
    for k, v in ref.items():
        np.testing.assert_array_equal(np.asarray(getattr(got, k)), v, err_msg=k)
    if strategy != "none":  # the oracle is not vacuous: some goals changed and some were reached
        assert 0 < ref["reward"].mean() + 1 < 1


def test_her_final_goal_of_a_running_segment_is_the_newest_state():
    buf = replay_init(_example(), 5, 1)  # 5 rows
    for t in range(7):  # one segment across the wrap
        x = jnp.full((1, OBS), float(t))
        buf = replay_add(buf, TrajStep(x, jnp.zeros((1, ACT)), x + 100, jnp.zeros((1, GOAL)),
                                       jnp.zeros(1, jnp.int32)))
    rows = jnp.arange(5, dtype=jnp.int32)
    tr = her_relabel(buf, rows, jnp.zeros(5, jnp.int32), jnp.zeros(5), jnp.zeros(5), "final", 1.0)
    np.testing.assert_array_equal(np.asarray(tr.goal), np.full((5, 2), 106.0))
    # the newest step's own achieved goal: reached, so reward 0 and no bootstrap
    newest = (int(buf.ptr) - 1) % 5
    assert float(tr.reward[newest]) == 0.0 and float(tr.discount[newest]) == 0.0
    assert float(tr.discount.sum()) == 4.0


def test_her_sample_draws_valid_entries_and_consistent_rewards():
    rng = np.random.default_rng(5)
    hist = _history(rng, 30, 4)
    buf = _fill(hist, 64, 4)
    tr = jax.jit(her_sample, static_argnames=("n", "strategy", "max_segment"))(
        jax.random.key(3), buf, n=512, strategy="future", relabel_prob=0.8, max_segment=200)
    d = np.linalg.norm(np.asarray(tr.next_obs)[:, :2] - np.asarray(tr.goal), axis=-1)
    np.testing.assert_array_equal(np.asarray(tr.reward), np.where(d <= 0.6, 0.0, -1.0))
    np.testing.assert_array_equal(np.asarray(tr.discount), np.where(d <= 0.6, 0.0, 1.0))
    rows, envs = replay_sample_index(buf, jax.random.key(4), 512)
    assert np.asarray(buf.valid)[np.asarray(rows), np.asarray(envs)].all()
    # jit and no-jit agree
    with jax.disable_jit():
        tr2 = her_sample(jax.random.key(3), buf, 512, "future", 0.8, 200)  # one op-by-op pass
    for a, b in zip(jax.tree_util.tree_leaves(tr), jax.tree_util.tree_leaves(tr2)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("steps,max_segment", [(9, 200), (61, 200), (61, 4), (20, 7)])
def test_her_index_equals_the_windowed_search(steps, max_segment):
    """her_index's once-per-buffer segment ends equal segment_last_offset at every valid entry
    (partly filled ring, wrap-around, invalid steps inside segments, the window), and sampling
    from the indexed buffer draws exactly what sampling from the replay draws."""
    rng = np.random.default_rng(100 + steps + max_segment)
    num_envs, capacity = 3, 60
    buf = _fill(_history(rng, steps, num_envs), capacity, num_envs)
    index = jax.jit(her_index, static_argnums=1)(buf, max_segment)
    rows, envs = np.nonzero(np.asarray(buf.valid))
    want = jax.jit(segment_last_offset, static_argnums=3)(
        buf, jnp.asarray(rows, jnp.int32), jnp.asarray(envs, jnp.int32), max_segment)
    got = np.asarray(index.last_offset)
    np.testing.assert_array_equal(got[rows, envs], np.asarray(want))
    assert (got[~np.asarray(buf.valid)] == 0).all()
    if steps > 20:  # the oracle is not vacuous: segments of several steps
        assert np.asarray(want).max() >= 2
    if max_segment == 4:  # and some reach past the window, which caps them
        assert np.asarray(want).max() == 3
    sample = jax.jit(her_sample, static_argnames=("n", "strategy", "max_segment"))
    for strategy in ("final", "future"):
        a = sample(jax.random.key(5), buf, n=256, strategy=strategy, max_segment=max_segment)
        b = sample(jax.random.key(5), index, n=256, strategy=strategy, max_segment=max_segment)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="indexed with max_segment"):
        her_sample(jax.random.key(5), index, 8, "final", max_segment=max_segment + 1)


@pytest.mark.parametrize("n,p", [(1, 1.0), (7, 0.0), (50, 0.3), (1000, 0.9), (1000, 1.0)])
def test_valid_positions_is_the_inverse_cdf_draw(n, p):
    """valid_positions(mask)[k] is the k-th True entry (NumPy's flatnonzero), the slots past the
    last one hold n - 1, and a draw through it equals the inverse-CDF search it replaces
    (searchsorted of the running count, clipped to the last slot), empty masks included."""
    rng = np.random.default_rng(n + int(10 * p))
    mask = rng.random(n) < p
    positions, size = jax.jit(valid_positions)(jnp.asarray(mask))
    want = np.flatnonzero(mask)
    assert int(size) == len(want)
    np.testing.assert_array_equal(np.asarray(positions)[:len(want)], want)
    assert (np.asarray(positions)[len(want):] == n - 1).all()
    k = rng.integers(0, max(len(want), 1), 4096)
    search = np.minimum(np.searchsorted(np.cumsum(mask), k, side="right"), n - 1)
    np.testing.assert_array_equal(np.asarray(positions)[k], search)


def test_replay_sample_index_draws_uniformly_over_valid_entries():
    """Every valid (row, env) entry is drawn, none invalid, each about equally often."""
    rng = np.random.default_rng(8)
    buf = _fill(_history(rng, 30, 4), 64, 4)
    valid = np.asarray(buf.valid)
    rows, envs = jax.jit(replay_sample_index, static_argnums=2)(buf, jax.random.key(9), 200_000)
    hits = np.zeros(valid.shape)
    np.add.at(hits, (np.asarray(rows), np.asarray(envs)), 1)
    assert (hits[~valid] == 0).all() and (hits[valid] > 0).all()
    expect = 200_000 / valid.sum()
    assert np.abs(hits[valid] / expect - 1).max() < 0.15

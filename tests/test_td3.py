"""Goal-conditioned TD3: NumPy oracles for the networks and targets, delayed updates, jit/no-jit,
no retracing, and a learning test (TD3+HER reaches goals in a point-mass arena)."""
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import envs
from dscpp_jax import td3 as td3_module
from dscpp_jax.her import her_sample
from dscpp_jax.replay import Transition, TrajStep, replay_add, replay_init
from dscpp_jax.td3 import (TD3Config, td3_act, td3_explore as _td3_explore, td3_init, td3_random_prob,
                           td3_target_noise, td3_targets, td3_update, td3_updates, td3_value)
from tests.numpy_nets import np_mlp, to_np

OBS, GOAL, ACT, B = 6, 2, 3, 64


def np_actor(cfg, params, obs, goal):
    a = np_mlp(to_np(params)["params"], np.concatenate([obs, goal], -1), len(cfg.hidden))
    if cfg.output_normalisation:
        return a / np.maximum(1.0, np.abs(a).mean(-1, keepdims=True))
    return cfg.max_action * np.tanh(a)


def np_twin_q(cfg, params, obs, goal, act):
    heads = to_np(params)["params"]["heads"]
    x = np.concatenate([obs, goal, act], -1)
    return np.stack([np_mlp(jax.tree_util.tree_map(lambda l: l[i], heads), x, len(cfg.hidden))[..., 0]
                     for i in range(2)])


# Jitted entry points: op-by-op dispatch would compile every primitive separately (slow on CPU).
_act = jax.jit(td3_act, static_argnums=0)
_value = jax.jit(td3_value, static_argnums=0)
_init = jax.jit(td3_init, static_argnums=(1, 2, 3, 4))
_noise = jax.jit(td3_target_noise, static_argnums=(0, 2))


@functools.partial(jax.jit, static_argnums=1)
def _batch_impl(key, n):
    k = jax.random.split(key, 6)
    return Transition(
        obs=jax.random.normal(k[0], (n, OBS)),
        action=jax.random.uniform(k[1], (n, ACT), minval=-1, maxval=1),
        reward=-(jax.random.uniform(k[2], (n,)) < 0.7).astype(jnp.float32),
        next_obs=jax.random.normal(k[3], (n, OBS)),
        goal=jax.random.normal(k[4], (n, GOAL)),
        discount=(jax.random.uniform(k[5], (n,)) < 0.8).astype(jnp.float32),
    )


def _batch(seed, n=B):
    return _batch_impl(jax.random.key(seed), n)


def _perturbed_state(cfg, seed=0):
    """Targets differ from the online nets (as after training), so mixing them up is caught."""
    st = _init(jax.random.key(seed), OBS, GOAL, ACT, cfg)
    noise = jax.jit(lambda p, s: jax.tree_util.tree_map(
        lambda x: x + 0.3 * jax.random.normal(jax.random.key(s), x.shape), p), static_argnums=1)
    return st.replace(target_actor_params=noise(st.target_actor_params, seed + 1),
                      target_critic_params=noise(st.target_critic_params, seed + 2))


CFGS = [TD3Config.model_free(hidden=(32, 32)), TD3Config.model_based(hidden=(32, 16))]


@pytest.mark.parametrize("cfg", CFGS, ids=["model_free", "model_based"])
def test_networks_and_targets_match_numpy(cfg):
    st = _perturbed_state(cfg)
    b = _batch(1)
    bn = to_np(b)
    # actor (tanh / output normalisation) and td3_act clipping
    a_ref = np_actor(cfg, st.actor_params, bn.obs, bn.goal)
    np.testing.assert_allclose(np.asarray(_act(cfg, st.actor_params, b.obs, b.goal)),
                               np.clip(a_ref, -1, 1), rtol=1e-4, atol=1e-5)
    # targets: r + gamma * c * min_i Q'_i(s', g, clip(pi'(s', g) + clip(noise)))
    noise = _noise(cfg, jax.random.key(7), b.action.shape)
    nz = np.asarray(noise, np.float64)
    assert np.abs(nz).max() <= cfg.noise_clip + 1e-6 and np.abs(nz).max() > 0.4  # clipped, not tiny
    a_next = np.clip(np_actor(cfg, st.target_actor_params, bn.next_obs, bn.goal) + nz, -1, 1)
    q_next = np_twin_q(cfg, st.target_critic_params, bn.next_obs, bn.goal, a_next).min(0)
    y_ref = bn.reward + 0.99 * bn.discount * q_next
    y = jax.jit(td3_targets, static_argnums=0)(cfg, st, b, noise)
    np.testing.assert_allclose(np.asarray(y), y_ref, rtol=1e-4, atol=1e-4)
    # value: min over the online twin critic at the online (clipped) action
    v_ref = np_twin_q(cfg, st.critic_params, bn.obs, bn.goal, np.clip(a_ref, -1, 1)).min(0)
    np.testing.assert_allclose(np.asarray(_value(cfg, st, b.obs, b.goal)), v_ref, rtol=1e-4, atol=1e-4)
    # the first head alone (what the actor's loss uses) is the twin critic's first output
    q1 = jax.jit(td3_module._q1, static_argnums=0)(cfg, st.critic_params, b.obs, b.goal, b.action)
    np.testing.assert_allclose(np.asarray(q1), np_twin_q(cfg, st.critic_params, bn.obs, bn.goal,
                                                         bn.action)[0], rtol=1e-4, atol=1e-4)


def test_target_range_clips_targets_like_numpy():
    base = TD3Config.model_based(hidden=(32, 16))
    cfg = TD3Config.model_based(hidden=(32, 16), target_range=(-0.5, 0.0))
    st = _perturbed_state(base)
    b = _batch(4)
    noise = _noise(base, jax.random.key(3), b.action.shape)
    y_free = np.asarray(jax.jit(td3_targets, static_argnums=0)(base, st, b, noise))
    y = np.asarray(jax.jit(td3_targets, static_argnums=0)(cfg, st, b, noise))
    assert (y_free < -0.5).any() and (y_free > -0.5).any()  # the range binds on part of the batch
    np.testing.assert_allclose(y, np.clip(y_free, -0.5, 0.0), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="target_range"):
        TD3Config(target_range=(0.0, -1.0))


def test_output_normalisation_bounds_mean_abs_action():
    cfg = TD3Config.model_based(hidden=(16,))
    st = _init(jax.random.key(0), OBS, GOAL, ACT, cfg)
    scaled = jax.tree_util.tree_map(lambda x: 50.0 * x, st.actor_params)  # large raw outputs
    b = _batch(2)
    a_raw = np_actor(TD3Config.model_free(hidden=(16,)), scaled, *map(np.asarray, (b.obs, b.goal)))
    a = np.asarray(_act(cfg, scaled, b.obs, b.goal))
    assert np.abs(np.arctanh(np.clip(a_raw, -0.999999, 0.999999))).mean() > 1.0
    assert np.all(np.abs(a).mean(-1) <= 1.0 + 1e-5)


def test_value_is_batched_over_any_leading_shape():
    cfg = CFGS[0]
    st = _init(jax.random.key(0), OBS, GOAL, ACT, cfg)
    obs = jax.random.normal(jax.random.key(1), (5, 7, OBS))
    goal = jax.random.normal(jax.random.key(2), (5, 7, GOAL))
    v = _value(cfg, st, obs, goal)
    assert v.shape == (5, 7)
    np.testing.assert_allclose(np.asarray(v[2]), np.asarray(_value(cfg, st, obs[2], goal[2])), rtol=1e-5)


def test_update_critic_loss_delay_and_polyak_targets():
    cfg = TD3Config.model_free(hidden=(32, 32), policy_delay=2, tau=0.1)
    st = _perturbed_state(cfg)
    b = _batch(3)
    update = jax.jit(td3_update, static_argnums=0)
    key = jax.random.key(11)
    s1, m1 = update(cfg, st, b, key)
    # critic loss = sum over heads of the mean squared TD error, with the same smoothing noise
    y = np.asarray(jax.jit(td3_targets, static_argnums=0)(cfg, st, b, _noise(cfg, key, b.action.shape)))
    q = np_twin_q(cfg, st.critic_params, *map(np.asarray, (b.obs, b.goal, b.action)))
    np.testing.assert_allclose(float(m1["critic_loss"]), ((q - y) ** 2).mean(-1).sum(), rtol=1e-4)
    # step 1: critic moved, actor and targets untouched
    same = lambda a, c: all(np.array_equal(np.asarray(x), np.asarray(z)) for x, z in
                            zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(c)))
    assert not same(s1.critic_params, st.critic_params)
    assert same(s1.actor_params, st.actor_params) and same(s1.target_critic_params, st.target_critic_params)
    assert float(m1["actor_updated"]) == 0.0 and int(s1.step) == 1
    # step 2: actor updated, targets = (1 - tau) * old target + tau * new online
    s2, m2 = update(cfg, s1, b, jax.random.key(12))
    assert float(m2["actor_updated"]) == 1.0 and not same(s2.actor_params, s1.actor_params)
    for tgt, old, onl in [(s2.target_actor_params, s1.target_actor_params, s2.actor_params),
                          (s2.target_critic_params, s1.target_critic_params, s2.critic_params)]:
        for t, o, n in zip(*(jax.tree_util.tree_leaves(to_np(p)) for p in (tgt, old, onl))):
            np.testing.assert_allclose(t, 0.9 * o + 0.1 * n, rtol=1e-5, atol=1e-6)
    # the actor step followed the policy gradient of Q1: Q1(s, pi(s)) went up on this batch
    q1 = lambda s: float(np.mean(np_twin_q(cfg, s.critic_params, np.asarray(b.obs), np.asarray(b.goal),
                                           np_actor(cfg, s.actor_params, np.asarray(b.obs),
                                                    np.asarray(b.goal)))[0]))
    assert q1(s2) > q1(s1.replace(critic_params=s2.critic_params))


def test_action_l2_adds_the_mean_squared_action_to_the_actor_loss():
    """actor loss = -mean Q1(s, pi(s)) + action_l2 * mean((pi / max_action)^2) (NumPy oracle), and
    the penalty pulls the deterministic actions towards zero."""
    b = _batch(5)
    obs, goal = np.asarray(b.obs), np.asarray(b.goal)
    update = jax.jit(td3_update, static_argnums=0)
    ends = {}
    for l2 in (0.0, 50.0):
        cfg = TD3Config.model_free(hidden=(32, 32), policy_delay=1, max_action=2.0, action_l2=l2)
        st = _perturbed_state(cfg)
        s1, m = update(cfg, st, b, jax.random.key(1))
        a = np_actor(cfg, st.actor_params, obs, goal)
        want = -np_twin_q(cfg, s1.critic_params, obs, goal, a)[0].mean() + l2 * ((a / 2.0) ** 2).mean()
        np.testing.assert_allclose(float(m["actor_loss"]), want, rtol=1e-4)
        for i in range(80):
            s1, _ = update(cfg, s1, b, jax.random.key(2 + i))
        ends[l2] = np.abs(np_actor(cfg, s1.actor_params, obs, goal)).mean()
    assert ends[50.0] < 0.5 * ends[0.0]
    with pytest.raises(ValueError, match="action_l2 must be >= 0"):
        TD3Config(action_l2=-1.0)


def test_jit_and_no_jit_agree():
    cfg = TD3Config.model_based(hidden=(16,), policy_delay=1)  # one call covers the actor branch
    st = _perturbed_state(cfg, seed=4)
    b = _batch(5)
    s_jit, m_jit = jax.jit(td3_update, static_argnums=0)(cfg, st, b, jax.random.key(0))
    with jax.disable_jit():
        s_py, m_py = td3_update(cfg, st, b, jax.random.key(0))
    assert float(m_py["actor_updated"]) == 1.0
    for a, c in zip(jax.tree_util.tree_leaves(s_jit), jax.tree_util.tree_leaves(s_py)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=2e-4, atol=1e-5)
    for k in m_jit:
        np.testing.assert_allclose(float(m_jit[k]), float(m_py[k]), rtol=2e-4, atol=1e-5)


def test_no_retracing_across_repeated_updates():
    cfg = CFGS[0]
    traces = {"update": 0, "updates": 0}
    ex = TrajStep(jnp.zeros(OBS), jnp.zeros(ACT), jnp.zeros(OBS), jnp.zeros(GOAL), jnp.zeros((), jnp.int32))
    buf = replay_init(ex, 64, 4)
    for t in range(8):
        x = jnp.full((4, OBS), float(t))
        buf = replay_add(buf, TrajStep(x, jnp.zeros((4, ACT)), x + 0.1, jnp.ones((4, GOAL)),
                                       jnp.zeros(4, jnp.int32)))

    @jax.jit
    def one(st, batch, key):
        traces["update"] += 1
        return td3_update(cfg, st, batch, key)

    @jax.jit
    def many(st, buffer, key):
        traces["updates"] += 1
        return td3_updates(cfg, st, buffer, key, 3, lambda k, b, n: her_sample(k, b, n, "future"))

    st = _init(jax.random.key(0), OBS, GOAL, ACT, cfg)
    for i in range(4):
        st, _ = one(st, _batch(i), jax.random.key(i))
        st, m = many(st, buf, jax.random.key(i))
    assert traces == {"update": 1, "updates": 1}
    assert int(st.step) == 16 and float(m["actor_updates"]) in (1.0, 2.0)


def test_sample_block_draws_several_minibatches_at_once_and_updates_in_order():
    """sample_block=3 over 7 steps: two blocks of 3 minibatches drawn by one sample call each,
    then one step sampling alone; the same as td3_update applied step by step to those batches."""
    cfg = TD3Config.model_free(hidden=(16,), batch_size=B)
    st0 = _perturbed_state(cfg, seed=6)
    calls = []

    def sample(k, buf, n):
        calls.append(n)
        return _batch_impl(k, n)

    key = jax.random.key(11)
    st, m = jax.jit(lambda s, k: td3_updates(cfg, s, None, k, 7, sample, sample_block=3))(st0, key)
    assert sorted(calls) == [B, 3 * B]            # traced once each: the block and the leftover

    upd = jax.jit(td3_update, static_argnums=0)
    ref, losses, n_actor = st0, [], 0.0
    k_blocks, k_rest = jax.random.split(key)
    steps = []
    for kb in jax.random.split(k_blocks, 2):
        ks, ku = jax.random.split(kb)
        big = _batch_impl(ks, 3 * B)
        for i, kk in enumerate(jax.random.split(ku, 3)):
            steps.append((jax.tree_util.tree_map(lambda x: x[i * B:(i + 1) * B], big), kk))
    for kr in jax.random.split(k_rest, 1):
        ks, ku = jax.random.split(kr)
        steps.append((_batch_impl(ks, B), ku))
    for batch, kk in steps:
        ref, mm = upd(cfg, ref, batch, kk)
        losses.append(float(mm["critic_loss"]))
        n_actor += float(mm["actor_updated"])
    assert int(st.step) == int(st0.step) + 7
    for a, c in zip(jax.tree_util.tree_leaves(st), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(m["critic_loss"]), np.mean(losses), rtol=1e-5)
    assert float(m["actor_updates"]) == n_actor == 3.0   # policy delay 2 over 7 steps
    with pytest.raises(ValueError, match="sample_block"):
        td3_updates(cfg, st0, None, key, 7, sample, sample_block=0)


@pytest.mark.parametrize("block", [1, 4])
def test_whole_delay_groups_place_the_actor_steps_without_a_branch(block):
    """8 steps (whole groups of policy_delay 2) from a step count of 0: the actor steps are placed
    on every second step with no lax.cond (on a GPU each one waits for the device), and the
    result is td3_update's step-count rule applied step by step. 7 steps keep the cond."""
    cfg = TD3Config.model_free(hidden=(16,), batch_size=B)
    st0 = _perturbed_state(cfg, seed=7)
    assert int(st0.step) == 0

    def sample(k, buf, n):
        return _batch_impl(k, n)

    def run(steps):
        return jax.jit(lambda s, k: td3_updates(cfg, s, None, k, steps, sample, sample_block=block))

    key = jax.random.key(12)
    st, m = run(8)(st0, key)
    # the same steps one by one, deciding the actor step by the step count
    steps = []
    if block == 1:
        for kk in jax.random.split(key, 8):
            ks, ku = jax.random.split(kk)
            steps.append((_batch_impl(ks, B), ku))
    else:
        for kb in jax.random.split(jax.random.split(key)[0], 8 // block):
            ks, ku = jax.random.split(kb)
            big = _batch_impl(ks, block * B)
            for i, kk in enumerate(jax.random.split(ku, block)):
                steps.append((jax.tree_util.tree_map(lambda x: x[i * B:(i + 1) * B], big), kk))
    upd = jax.jit(td3_update, static_argnums=0)
    ref, n_actor = st0, 0.0
    for batch, kk in steps:
        ref, mm = upd(cfg, ref, batch, kk)
        n_actor += float(mm["actor_updated"])
    assert int(st.step) == 8 and float(m["actor_updates"]) == n_actor == 4.0
    for a, c in zip(jax.tree_util.tree_leaves(st), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-5, atol=1e-6)
    # the placed program has no conditional; 7 steps (not whole groups) decide per step
    text = run(8).lower(st0, key).as_text()
    assert "stablehlo.case" not in text and "stablehlo.if" not in text
    assert "stablehlo.case" in run(7).lower(st0, key).as_text()


def test_exploration_and_config():
    cfg = TD3Config.model_free(hidden=(16,))
    td3_explore = jax.jit(_td3_explore, static_argnums=0)
    st = _init(jax.random.key(0), OBS, GOAL, ACT, cfg)
    b = _batch(6, n=4000)
    det = np.asarray(_act(cfg, st.actor_params, b.obs, b.goal))
    a0 = td3_explore(cfg, st.actor_params, jax.random.key(1), b.obs, b.goal, random_prob=0.0, noise_std=0.0)
    np.testing.assert_allclose(np.asarray(a0), det, rtol=1e-6)
    noisy = np.asarray(td3_explore(cfg, st.actor_params, jax.random.key(1), b.obs, b.goal, random_prob=0.0))
    assert abs(np.std(noisy - det) - 0.1) < 0.01  # Gaussian N(0, 0.1) (actions far from the bounds)
    a = np.asarray(td3_explore(cfg, st.actor_params, jax.random.key(1), b.obs, b.goal, random_prob=0.3))
    assert np.all(np.abs(a) <= 1.0)
    rand = np.any(a != noisy, axis=-1)  # same key: rows either keep the noisy action or are random
    assert 0.27 < rand.mean() < 0.33
    assert np.abs(a[rand]).mean() == pytest.approx(0.5, abs=0.03)  # uniform in [-1, 1]
    assert float(td3_random_prob(cfg, 0)) == pytest.approx(0.8) and float(td3_random_prob(cfg, 3)) == pytest.approx(0.2)
    mb = TD3Config.model_based()
    assert (mb.actor_lr, mb.critic_lr, mb.output_normalisation) == (1e-5, 1e-5, True)
    assert float(td3_random_prob(mb, 0)) == pytest.approx(0.1)
    mf = TD3Config.model_free(batch_size=100)  # the paper table's batch size
    assert (mf.actor_lr, mf.batch_size, mf.discount, mf.tau, mf.policy_delay) == (3e-4, 100, 0.99, 0.005, 2)
    assert hash(mf) == hash(TD3Config.model_free(batch_size=100, hidden=[256, 256]))
    with pytest.raises(ValueError, match="policy_delay"):
        TD3Config(policy_delay=0)


# ---------------------------------------------------------------------------------------------
# learning test: TD3 + HER ("future") in an open point-mass arena (free space (-4.5, 4.5)^2)
ARENA = "#####\n#..g#\n#.r.#\n#...#\n#####"
N_ENVS, EPISODE, ITERS, STEPS_PER_ITER, UPDATES_PER_ITER = 16, 40, 400, 4, 24
EVAL_LEN = 60
_ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
EVAL_STARTS = np.stack([3.5 * np.cos(_ang), 3.5 * np.sin(_ang)], 1).astype(np.float32)
EVAL_GOALS = np.stack([3.0 * np.cos(_ang + 2.5), 3.0 * np.sin(_ang + 2.5)], 1).astype(np.float32)


def _make_learning_run(env, cfg):
    def new_episode(key):
        ks, kg, kr = jax.random.split(key, 3)
        start = env.layout.sample_free(ks, jnp.array([1e3, 1e3]), margin=0.5)
        goal = env.layout.sample_free(kg, start, margin=0.5)
        st = env.reset_at(kr, start)
        return st.replace(info=dict(st.info, goal=goal))

    def env_step(carry, key):
        td3, buf, est, seg = carry
        ka, kr = jax.random.split(key)
        goal = est.info["goal"]
        a = _td3_explore(cfg, td3.actor_params, ka, est.obs, goal)
        nst = jax.vmap(env.step)(est, a)
        buf = replay_add(buf, TrajStep(est.obs, a, nst.obs, goal, seg))
        done = nst.done > 0
        fresh = jax.vmap(new_episode)(jax.random.split(kr, N_ENVS))
        nst = jax.tree_util.tree_map(
            lambda f, o: jnp.where(done.reshape(done.shape + (1,) * (o.ndim - 1)), f, o), fresh, nst)
        return (td3, buf, nst, seg + done.astype(jnp.int32)), None

    sample = lambda k, b, n: her_sample(k, b, n, strategy="future", relabel_prob=0.8,
                                        max_segment=EPISODE, goal_tolerance=env.goal_tolerance)

    def iteration(carry, key):
        kc, ku = jax.random.split(key)
        carry, _ = jax.lax.scan(env_step, carry, jax.random.split(kc, STEPS_PER_ITER))
        td3, buf, est, seg = carry
        td3, m = td3_updates(cfg, td3, buf, ku, UPDATES_PER_ITER, sample)
        return (td3, buf, est, seg), m["critic_loss"]

    @jax.jit
    def train(key):
        k0, k1, k2 = jax.random.split(key, 3)
        td3 = td3_init(k0, env.observation_size, env.goal_size, env.action_size, cfg)
        ex = TrajStep(jnp.zeros(4), jnp.zeros(2), jnp.zeros(4), jnp.zeros(2), jnp.zeros((), jnp.int32))
        carry = (td3, replay_init(ex, 50_000, N_ENVS), jax.vmap(new_episode)(jax.random.split(k1, N_ENVS)),
                 jnp.zeros(N_ENVS, jnp.int32))
        carry, losses = jax.lax.scan(iteration, carry, jax.random.split(k2, ITERS))
        return carry[0], losses

    @jax.jit
    def evaluate(actor_params, key):
        def one(start, goal, k):
            st = env.reset_at(k, start)
            st = st.replace(info=dict(st.info, goal=goal))

            def body(c, _):
                st, hit = c
                st = env.step(st, td3_act(cfg, actor_params, st.obs, goal))
                return (st, hit | (st.info["success"] > 0)), None

            (_, hit), _ = jax.lax.scan(body, (st, jnp.zeros((), bool)), None, length=EVAL_LEN)
            return hit

        return jax.vmap(one)(jnp.asarray(EVAL_STARTS), jnp.asarray(EVAL_GOALS),
                             jax.random.split(key, len(EVAL_STARTS)))

    return train, evaluate


def test_td3_her_learns_to_reach_goals_in_point_arena():
    env = envs.make_from_map(ARENA, 3.0, robot="point", episode_length=EPISODE)
    cfg = TD3Config.model_free(hidden=(64, 64), actor_lr=1e-3, critic_lr=1e-3,
                               random_action_prob=0.2, random_action_prob_start=0.2)
    train, evaluate = _make_learning_run(env, cfg)
    t0, c0 = time.time(), time.process_time()
    td3, losses = train(jax.random.key(0))
    jax.block_until_ready(td3)
    wall, cpu = time.time() - t0, time.process_time() - c0
    trained = np.asarray(evaluate(td3.actor_params, jax.random.key(1)))
    untrained = [np.asarray(evaluate(_init(jax.random.key(s), 4, 2, 2, cfg).actor_params,
                                     jax.random.key(1))).mean() for s in range(3)]
    print(f"\nTD3+HER point arena: success {trained.mean():.2f} (untrained {np.mean(untrained):.2f}); "
          f"{ITERS * STEPS_PER_ITER * N_ENVS} env steps, {ITERS * UPDATES_PER_ITER} updates, "
          f"{wall:.1f} s wall / {cpu:.1f} s CPU incl. compile")
    assert np.isfinite(np.asarray(losses)).all()
    assert trained.mean() >= 0.8, trained
    assert np.mean(untrained) <= 0.2, untrained


def test_bfloat16_compute_keeps_float32_state_and_close_values():
    """compute_dtype="bfloat16": the hidden layers compute in bf16 but parameters, optimiser
    state, Q values, targets and losses stay float32, and the values are the float32 ones to bf16
    accuracy."""
    f32, bf = TD3Config.model_free(hidden=(32, 32)), TD3Config.model_free(hidden=(32, 32),
                                                                         compute_dtype="bfloat16")
    st = _perturbed_state(f32)
    b = _batch(2)
    v32, vbf = _value(f32, st, b.obs, b.goal), _value(bf, st, b.obs, b.goal)
    assert vbf.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(vbf), np.asarray(v32), rtol=0.05, atol=0.05)
    assert not np.array_equal(np.asarray(vbf), np.asarray(v32))   # it did compute in bf16
    s1, m = jax.jit(td3_update, static_argnums=0)(bf, st, b, jax.random.key(0))
    assert all(x.dtype in (jnp.float32, jnp.int32) for x in jax.tree_util.tree_leaves(s1))
    assert all(np.isfinite(float(v)) for v in m.values())
    with pytest.raises(ValueError, match="compute_dtype"):
        TD3Config(compute_dtype="float16")


def _dot_operand_dtypes(fn, *args):
    """The operand dtypes of every dot_general in fn's jaxpr, in program order."""
    out = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                out.append(tuple(str(v.aval.dtype) for v in eqn.invars))
            for v in eqn.params.values():
                if hasattr(v, "jaxpr") and hasattr(v.jaxpr, "eqns"):
                    walk(v.jaxpr)
                elif hasattr(v, "eqns"):
                    walk(v)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return out


def test_bfloat16_keeps_positions_and_q_values_at_float32_resolution():
    """"bfloat16" runs the first layer's product and the output layer in float32: Q values near
    -60, where bf16's spacing is 0.25 (a quarter of one step's reward), come out within float32
    rounding of the hidden layers' bf16 error, not on bf16's grid (every layer in bf16 put each
    value on it, up to 0.125 off)."""
    f32 = TD3Config.model_free(hidden=(32, 32))
    bf = TD3Config.model_free(hidden=(32, 32), compute_dtype="bfloat16")
    st = _perturbed_state(f32)
    heads = st.critic_params["params"]["heads"]
    out = {**heads["out"], "bias": heads["out"]["bias"] - 60.0}
    st = st.replace(critic_params={"params": {"heads": {**heads, "out": out}}})
    b = _batch(3, 256)
    v32 = np.asarray(_value(f32, st, b.obs, b.goal))
    vbf = np.asarray(_value(bf, st, b.obs, b.goal))
    assert (v32 < -55).all()
    assert np.mean(np.mod(vbf * 4.0, 1.0) == 0.0) < 0.1     # not multiples of 0.25
    assert np.abs(vbf - v32).max() < 0.06
    # which products run in bf16: a critic head's layers are the first, the hidden, the output
    q = lambda c, p: td3_module._q(c, p, b.obs, b.goal, b.action)
    for cfg, want in ((f32, ["float32", "float32", "float32"]),
                      (bf, ["float32", "bfloat16", "float32"])):
        got = _dot_operand_dtypes(functools.partial(q, cfg), st.critic_params)
        assert [d[0] for d in got] == want, (cfg.compute_dtype, got)
        assert all(x == w for x, w in got), got

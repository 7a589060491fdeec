"""The learners of the paper's baselines: one TD3 per option slot (dsc and dual: region policies
on the observation alone; mf_dscpp with shared_critic=false: goal-conditioned). The region update
against a NumPy reference, each option learning only from its own transitions (one step per own
new transition) while the global option learns from all, new options starting as the global
option's copy, the per-option exploration schedule, region success and the global option's
timeout. dsc learning the point-mass U-maze is in tests/test_learning.py, with the other learning
runs (at XLA's full optimisation, under which they execute faster)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import acting as A
from dscpp_jax import learning as L
from dscpp_jax import trainer as T
from dscpp_jax.options import FREE, GESTATION, MATURE
from dscpp_jax.replay import RegionStep, replay_add, replay_group_index, replay_init
from dscpp_jax.td3 import (td3_copy_option, td3_init_per_option, td3_option, td3_set_option,
                           td3_target_noise, td3_updates, td3_updates_options)
from dscpp_jax.td3 import TD3Config
from tests.numpy_nets import np_mlp, to_np
from tests.trainer_fixtures import tiny

OBS, ACT, K, NE, ROWS = 4, 2, 4, 4, 12
OPTION_OF_ENV = (0, 1, 1, 2)      # env column e ran option OPTION_OF_ENV[e]; option 3 never ran


def _config(algo="dsc", **kw):
    base = dict(max_options=K, steps_per_iter=4, td3_updates_per_step=1.0, td3_batch_size=8,
                td3_hidden=16, td3_sample_block=1)
    base.update(kw)
    return tiny(algo, **base)


def _replay(seed, perturb_option=None, goal_dim=2):
    """ROWS x NE transitions of OPTION_OF_ENV; obs[..., 0] holds the option id so a sample's origin
    is visible; in_target and at_goal are random flags. ``perturb_option``: that option's data
    (observations, actions, flags) differ, everything else is the same."""
    rng = np.random.default_rng(seed)
    opt = np.broadcast_to(np.asarray(OPTION_OF_ENV, np.int32), (ROWS, NE))
    obs = rng.normal(size=(ROWS, NE, OBS)).astype(np.float32)
    nxt = obs + 0.1 * rng.normal(size=obs.shape).astype(np.float32)
    act = rng.uniform(-1, 1, size=(ROWS, NE, ACT)).astype(np.float32)
    tgt = rng.uniform(size=(ROWS, NE)) < 0.3
    at_goal = rng.uniform(size=(ROWS, NE)) < 0.2
    if perturb_option is not None:
        m = opt == perturb_option
        other = np.random.default_rng(seed + 100)
        obs = np.where(m[..., None], other.normal(size=obs.shape), obs).astype(np.float32)
        nxt = np.where(m[..., None], other.normal(size=obs.shape), nxt).astype(np.float32)
        tgt = np.where(m, ~tgt, tgt)
        at_goal = np.where(m, ~at_goal, at_goal)
    obs[..., 0] = opt
    nxt[..., 0] = opt
    seg = np.broadcast_to((np.arange(ROWS) // 4)[:, None], (ROWS, NE)).astype(np.int32)
    f = jnp.zeros((), bool)
    ex = RegionStep(jnp.zeros(OBS), jnp.zeros(ACT), jnp.zeros(OBS), jnp.zeros(goal_dim),
                  jnp.zeros((), jnp.int32), option=jnp.zeros((), jnp.int32), in_target=f,
                  at_goal=f)
    buf = replay_init(ex, ROWS * NE, NE)
    goal = rng.normal(size=(ROWS, NE, goal_dim)).astype(np.float32)
    for t in range(ROWS):
        buf = replay_add(buf, RegionStep(jnp.asarray(obs[t]), jnp.asarray(act[t]),
                                       jnp.asarray(nxt[t]), jnp.asarray(goal[t]),
                                       jnp.asarray(seg[t]), option=jnp.asarray(opt[t]),
                                       in_target=jnp.asarray(tgt[t]),
                                       at_goal=jnp.asarray(at_goal[t])))
    return buf, tgt, at_goal


# ------------------------------------------------------------------------------------------------
# NumPy reference of the region TD3's networks and targets (as tests/test_td3.py's oracle)
# ------------------------------------------------------------------------------------------------
def np_actor(params, obs, n_hidden=2):
    return np.tanh(np_mlp(to_np(params)["params"], obs, n_hidden))      # no goal input


def np_twin_q(params, obs, act, n_hidden=2):
    heads = to_np(params)["params"]["heads"]
    x = np.concatenate([obs, act], -1)
    return np.stack([np_mlp(jax.tree_util.tree_map(lambda l: l[i], heads), x, n_hidden)[..., 0]
                     for i in range(2)])


def test_region_td3_update_matches_numpy():
    cfg = _config()
    tcfg = TD3Config.from_section(cfg.td3, cfg.model_based)
    buf, tgt, _ = _replay(0, goal_dim=2)
    index = replay_group_index(buf, buf.data.option, K)
    states = jax.jit(lambda k: td3_init_per_option(k, K, OBS, 0, ACT, tcfg))(jax.random.key(0))
    own, _ = L.option_sample_fns(cfg, buf)
    steps = jnp.asarray([0, 0, 1, 0])          # one step of option 2, nothing else
    key = jax.random.key(7)
    run = jax.jit(lambda s, k: td3_updates_options(tcfg, s, steps, k, 3, own, 1))
    new, m = run(states, key)
    # the same minibatch and smoothing noise as the round that ran (round 0)
    kk = jax.random.split(key, 3)[0]
    k_s, k_u = jax.random.split(kk)
    batch = jax.jit(lambda k: own(k, jnp.asarray(2), tcfg.batch_size))(k_s)
    noise = np.asarray(td3_target_noise(tcfg, jax.random.split(k_u, 1)[0], batch.action.shape))
    b = jax.tree_util.tree_map(np.asarray, batch)
    assert b.goal.shape == (tcfg.batch_size, 0)
    assert np.all(b.obs[:, 0] == 2)                      # option 2's own transitions
    # reward -1, and 0 with no bootstrap where the next state is in the target region
    done = b.reward == 0.0
    np.testing.assert_array_equal(b.discount, 1.0 - done)
    assert set(np.unique(b.reward)) <= {-1.0, 0.0}
    assert done.any() and (~done).any(), "the fixture should give both kinds"
    st = td3_option(states, 2)
    a_next = np.clip(np_actor(st.target_actor_params, b.next_obs) + noise, -1, 1)
    q_next = np_twin_q(st.target_critic_params, b.next_obs, a_next).min(0)     # twin minimum
    y = b.reward + tcfg.discount * b.discount * q_next
    q = np_twin_q(st.critic_params, b.obs, b.action)
    np.testing.assert_allclose(float(m["critic_loss"]), ((q - y) ** 2).mean(-1).sum(), rtol=1e-4)
    np.testing.assert_allclose(float(m["target_mean"]), y.mean(), rtol=1e-4, atol=1e-6)
    assert float(m["option_steps"]) == 1.0 and float(m["options_learning"]) == 1.0
    # only option 2's TD3 moved, by one critic step
    np.testing.assert_array_equal(np.asarray(new.step), [0, 0, 1, 0])
    for o in (0, 1, 3):
        for x, z in zip(jax.tree_util.tree_leaves(td3_option(new, o)),
                        jax.tree_util.tree_leaves(td3_option(states, o))):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(z))
    # the region targets come from the stored flags: option 2's rows of in_target
    assert tgt[:, 3].any()


@pytest.mark.parametrize("algo,kw", [("dsc", {}), ("mf_dscpp", dict(shared_critic=False))])
def test_options_learn_from_their_own_transitions_and_the_global_option_from_all(algo, kw):
    cfg = _config(algo, **kw)
    goal_dim = 0 if cfg.option_policies == "region" else 2
    buf, _, _ = _replay(1)
    # one step per own transition of this iteration (the last steps_per_iter = 4 rows): options 1
    # and 2 ran 8 and 4 of them; the global option's steps are its own
    np.testing.assert_array_equal(np.asarray(L.option_steps(cfg, buf)), [0, 8, 4, 0])
    own, everything = L.option_sample_fns(cfg, buf)
    for o in (1, 2):
        b = jax.jit(lambda k: own(k, jnp.asarray(o), 64))(jax.random.key(o))
        assert np.all(np.asarray(b.obs)[:, 0] == o)
    b = jax.jit(lambda k: everything(k, 256))(jax.random.key(3))
    assert set(np.unique(np.asarray(b.obs)[:, 0]).tolist()) == {0.0, 1.0, 2.0}
    if cfg.option_policies == "region":   # the global option's reward is the task's
        assert np.asarray(b.goal).shape == (256, 0)

    tcfg = TD3Config.from_section(cfg.td3, cfg.model_based)
    states = jax.jit(lambda k: td3_init_per_option(k, K, OBS, goal_dim, ACT, tcfg))(
        jax.random.key(0))
    update = jax.jit(lambda s, r, k: L.update_option_policies(cfg, s, r, k))
    new, m = update(states, buf, jax.random.key(5))
    np.testing.assert_array_equal(np.asarray(new.step), [cfg.td3_updates, 8, 4, 0])
    assert float(m["td3/option_steps"]) == 12 and float(m["td3/options_learning"]) == 2
    # other data of option 2 (and so of the global option): option 1 learns exactly the same,
    # option 2 and the global option do not
    other, _, _ = _replay(1, perturb_option=2)
    new2, _ = update(states, other, jax.random.key(5))
    leaf = lambda s, o: np.asarray(td3_option(s, o).critic_params["params"]["heads"]["out"]["kernel"])
    np.testing.assert_array_equal(leaf(new, 1), leaf(new2, 1))
    assert not np.array_equal(leaf(new, 2), leaf(new2, 2))
    assert not np.array_equal(leaf(new, 0), leaf(new2, 0))
    np.testing.assert_array_equal(leaf(new, 3), leaf(states, 3))   # never ran: as initialised


@pytest.mark.parametrize("option_init", ["copy_global", "random"])
def test_a_new_option_starts_as_the_global_option_with_copy_global(option_init):
    cfg = _config("mf_dscpp", shared_critic=False, option_init=option_init)
    tcfg = TD3Config.from_section(cfg.td3, cfg.model_based)
    buf, _, _ = _replay(2)
    states = jax.jit(lambda k: td3_init_per_option(k, K, OBS, 2, ACT, tcfg))(jax.random.key(0))
    trained, _ = jax.jit(lambda s, r, k: L.update_option_policies(cfg, s, r, k))(
        states, buf, jax.random.key(1))
    before = jnp.asarray([3, GESTATION, FREE, FREE])     # the global option is ALWAYS (3)
    after = jnp.asarray([3, MATURE, GESTATION, FREE])   # row 2 created
    out = jax.jit(lambda s: L.init_new_options(cfg, s, before, after))(trained)
    g, new = td3_option(trained, 0), td3_option(out, 2)
    nets = ("actor_params", "critic_params", "target_actor_params", "target_critic_params")
    same = lambda a, b: all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
                            zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    if option_init == "copy_global":
        assert all(same(getattr(new, n), getattr(g, n)) for n in nets)
        fresh = jax.jit(lambda k: td3_init_per_option(k, 1, OBS, 2, ACT, tcfg))(jax.random.key(9))
        assert all(float(jnp.max(jnp.abs(x))) == 0.0 for x in jax.tree_util.tree_leaves(
            (new.actor_opt_state, new.critic_opt_state)) if x.dtype != jnp.int32)
        assert int(new.step) == 0 and jax.tree_util.tree_structure(new.actor_opt_state) == \
            jax.tree_util.tree_structure(td3_option(fresh, 0).actor_opt_state)
    else:
        assert not same(new.actor_params, g.actor_params)
        assert same(new, td3_option(trained, 2))
    # the rows that existed keep their networks (the goal option is never copied)
    for o in (0, 1, 3):
        assert same(td3_option(out, o), td3_option(trained, o))
    # the copy as a function of the table: no row created, nothing changes
    assert same(td3_copy_option(tcfg, trained, 0, jnp.zeros((K,), bool)), trained)


def test_exploration_counts_the_executing_options_own_successes():
    cfg = _config("dsc", random_action_prob=0.2)
    chain = type("C", (), {"successes": jnp.asarray([4, 3, 0, 9])})()
    p = A.random_action_probs(cfg, chain, jnp.asarray([0, 1, 2, 3, -1]), jnp.asarray(100))
    # MFOptionClass._get_epsilon: 0.8 while num_goal_hits <= 3, else 0.2
    np.testing.assert_allclose(np.asarray(p), [0.2, 0.8, 0.8, 0.2, 0.2])
    # DSC++ keeps the run-wide switch
    q = A.random_action_probs(_config("mf_dscpp"), chain, jnp.asarray([2]), jnp.asarray(3))
    assert float(q) == pytest.approx(0.2)


def test_region_options_succeed_anywhere_in_their_target_and_the_global_option_steps_once():
    cfg = _config("dual")
    assert cfg.effective_global_option_timeout == 1
    env = T.make_env(cfg)
    chain = T.init(jax.random.PRNGKey(0), cfg.override(max_options=K)).chain
    goal = np.asarray(env.goal, np.float32)
    ex = A.exec_init(cfg, jnp.zeros((3, env.observation_size)), goal)
    # global option after one step away from the goal: timed out; goal option at the goal with a
    # subgoal elsewhere: success (the region, not the point); goal option away from it: running
    ex = ex.replace(option=jnp.asarray([0, 1, 1]), opt_steps=jnp.asarray([1, 1, 1]),
                    subgoal=jnp.asarray([goal, goal + 5.0, goal], jnp.float32))
    xy = jnp.asarray([goal + 3.0, goal, goal + 3.0], jnp.float32)
    ended, success = jax.jit(lambda e, p: A.option_end(cfg, env, chain, e, p, jnp.zeros(3)))(ex, xy)
    np.testing.assert_array_equal(np.asarray(ended), [True, True, False])
    np.testing.assert_array_equal(np.asarray(success), [False, True, False])


def _sequential_option_updates(cfg, td3, replay, key, seed_axis=None):
    """The options' steps and then the global option's, one after the other: the reference
    for the pass that runs them side by side."""
    tcfg = TD3Config.from_section(cfg.td3, cfg.model_based)
    own, everything = L.option_sample_fns(cfg, replay)
    k_own, k_glob = jax.random.split(key)
    block = cfg.td3.sample_block
    td3, om = td3_updates_options(tcfg, td3, L.option_steps(cfg, replay), k_own,
                                  -(-cfg.td3_updates // block), own, sample_block=block,
                                  seed_axis=seed_axis)
    glob, gm = td3_updates(tcfg, td3_option(td3, L.GLOBAL_ROW), None, k_glob, cfg.td3_updates,
                           lambda k, _, n: everything(k, n), sample_block=block,
                           seed_axis=seed_axis)
    td3 = td3_set_option(td3, L.GLOBAL_ROW, glob)
    m = {f"td3/{k}": v for k, v in om.items()}
    m.update({f"td3/global_{k}": v for k, v in gm.items()})
    return td3, m


@pytest.mark.parametrize("algo,kw,grouped", [
    ("dsc", dict(td3_sample_block=4), True),
    ("mf_dscpp", dict(shared_critic=False, td3_sample_block=1), False)])
def test_the_global_option_learning_beside_the_options_takes_the_same_steps(algo, kw, grouped):
    cfg = _config(algo, **kw)
    assert cfg.td3_updates % cfg.td3.sample_block == 0     # the side-by-side pass
    goal_dim = 0 if cfg.option_policies == "region" else 2
    tcfg = TD3Config.from_section(cfg.td3, cfg.model_based)
    states = jax.jit(lambda k: td3_init_per_option(k, K, OBS, goal_dim, ACT, tcfg))(
        jax.random.key(0))
    buf, _, _ = _replay(3)

    def close(a, b):
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)

    fused = jax.jit(lambda s, r, k: L.update_option_policies(cfg, s, r, k))
    one_after = jax.jit(lambda s, r, k: _sequential_option_updates(cfg, s, r, k))
    for step in range(2):       # a second call starts from trained states and step counts
        key = jax.random.key(11 + step)
        new, m = fused(states, buf, key)
        ref, mr = one_after(states, buf, key)
        assert sorted(m) == sorted(mr)
        close(new, ref)
        close(m, {k: mr[k] for k in m})
        states = new
    assert int(td3_option(states, L.GLOBAL_ROW).step) == 2 * cfg.td3_updates
    assert float(m["td3/option_steps"]) > 0
    if not grouped:
        return
    # under a vmap over seeds (the seed group), where a round runs when any seed runs it
    bufs = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), buf, _replay(4)[0])
    st2 = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), states)
    keys = jax.random.split(jax.random.key(21), 2)
    group = lambda f: jax.jit(jax.vmap(lambda s, r, k: f(cfg, s, r, k, seed_axis="seed"),  # noqa: E731
                                       axis_name="seed"))
    new, m = group(L.update_option_policies)(st2, bufs, keys)
    ref, mr = group(_sequential_option_updates)(st2, bufs, keys)
    close(new, ref)
    close(m, {k: mr[k] for k in m})


@pytest.mark.parametrize("env", ["u_maze", "medium", "four_rooms", "ant_reacher"])
@pytest.mark.parametrize("algo,kw", [("dsc", {}), ("dual", {}),
                                     ("mf_dscpp", dict(shared_critic=False))])
def test_the_ant_presets_take_the_side_by_side_pass(env, algo, kw):
    """The ant presets' per-option learners take whole sample blocks per iteration, so the
    global option's steps run beside the options' (`update_option_policies`)."""
    from dscpp_jax.config import preset
    cfg = preset("fast", env, algo, **kw)
    assert cfg.per_option_td3 and cfg.td3.sample_block > 1
    assert cfg.td3_updates % cfg.td3.sample_block == 0

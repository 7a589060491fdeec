"""One TD3 per option (`Config.td3.shared_critic=False`, the paper's appendix Figure 2): the option
axis, options that never ran keep their initial networks, each option learns only from its own
transitions, acting and evaluation use the running option's actor, and MF-DSC++ trains, evaluates
and resumes from a checkpoint exactly."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscpp_jax
from dscpp_jax import checkpoint as ck
from dscpp_jax import acting as A
from dscpp_jax import trainer as T
from dscpp_jax.her import her_sample
from dscpp_jax.replay import TrajStep, replay_add, replay_init
from dscpp_jax.td3 import TD3Config, td3_act, td3_init, td3_init_per_option, td3_option
from tests.trainer_fixtures import assert_trees_equal, tiny

OBS, GOAL, ACT, K, NE, ROWS = 4, 2, 2, 3, 4, 12
CFG = TD3Config.model_free(hidden=(16, 16), batch_size=16)


def _buffer(seed, option_of_env=(1, 1, 2, 2), extra=None):
    """ROWS x NE transitions; env e's column ran option ``option_of_env[e]`` (segments of 4 steps).
    obs[..., 0] holds the option id so a sample's origin is visible. ``extra``: (option, scale)
    adds ``scale`` noise to that option's observations, actions and goals (other data unchanged)."""
    rng = np.random.default_rng(seed)
    opt = np.broadcast_to(np.asarray(option_of_env, np.int32), (ROWS, NE))
    obs = rng.normal(size=(ROWS, NE, OBS)).astype(np.float32)
    nxt = obs + 0.1 * rng.normal(size=obs.shape).astype(np.float32)
    act = rng.uniform(-1, 1, size=(ROWS, NE, ACT)).astype(np.float32)
    goal = rng.normal(size=(ROWS, NE, GOAL)).astype(np.float32)
    if extra is not None:
        o, scale = extra
        m = (opt == o)[..., None]
        obs = obs + m * scale * rng.normal(size=obs.shape).astype(np.float32)
        nxt = nxt + m * scale * rng.normal(size=nxt.shape).astype(np.float32)
        act = np.clip(act + m * scale * rng.normal(size=act.shape).astype(np.float32), -1, 1)
        goal = goal + m * scale * rng.normal(size=goal.shape).astype(np.float32)
    obs[..., 0] = opt
    nxt[..., 0] = opt
    seg = np.broadcast_to((np.arange(ROWS) // 4)[:, None], (ROWS, NE)).astype(np.int32)
    ex = TrajStep(jnp.zeros(OBS), jnp.zeros(ACT), jnp.zeros(OBS), jnp.zeros(GOAL),
                  jnp.zeros((), jnp.int32), option=jnp.zeros((), jnp.int32))
    buf = replay_init(ex, ROWS * NE, NE)
    for t in range(ROWS):
        buf = replay_add(buf, TrajStep(jnp.asarray(obs[t]), jnp.asarray(act[t]), jnp.asarray(nxt[t]),
                                       jnp.asarray(goal[t]), jnp.asarray(seg[t]),
                                       option=jnp.asarray(opt[t])))
    return buf


def test_masked_view_samples_only_that_options_transitions():
    buf = _buffer(1, option_of_env=(0, 1, 2, 1))
    for o in range(K):
        view = buf.replace(valid=buf.valid & (buf.data.option == o))
        tr = jax.jit(lambda k, b: her_sample(k, b, 256, "future", max_segment=4))(
            jax.random.key(o), view)
        np.testing.assert_array_equal(np.asarray(tr.obs[:, 0]), o)
        # relabelled goals stay inside the option's own segments
        achieved = np.asarray(buf.data.next_obs[..., :GOAL])[np.asarray(buf.data.option) == o]
        relabelled = np.asarray(tr.goal)
        own = (np.abs(relabelled[:, None] - achieved[None]).sum(-1) == 0).any(1)
        pursued = np.asarray(buf.data.goal)[np.asarray(buf.data.option) == o]
        kept = (np.abs(relabelled[:, None] - pursued[None]).sum(-1) == 0).any(1)
        assert np.all(own | kept)


# per-option critics end to end: DP subgoals (each option's critic scores its subgoals and its row
# of the table) and in-band evaluation on. The tests below share its init and train_step programs.
_E2E = tiny("mf_dscpp", shared_critic=False, subgoal="dp", warmup_episodes=0, inband_eval_envs=2)


def test_each_env_acts_with_its_options_actor():
    cfg = _E2E
    s = T.init(jax.random.PRNGKey(0), cfg)
    tcfg = TD3Config.from_section(s.config.td3, s.config.model_based)
    obs = jax.random.normal(jax.random.key(1), (5, s.env_state.obs.shape[-1]))
    goals = jax.random.normal(jax.random.key(2), (5, 2))
    options = jnp.asarray([0, 1, 2, 3, T.NO_OPTION], jnp.int32)
    acts = jax.jit(lambda td3: A.policy_actions(s.config, td3, None, obs, goals, None, False, 0.0,
                                                 options))(s.td3)
    for i, o in enumerate([0, 1, 2, 3, 0]):
        want = td3_act(tcfg, td3_option(s.td3, o).actor_params, obs[i:i + 1], goals[i:i + 1])[0]
        np.testing.assert_allclose(np.asarray(acts[i]), np.asarray(want), rtol=1e-5, atol=1e-6)


def test_model_based_with_per_option_critics_is_rejected():
    with pytest.raises(ValueError, match="shared_critic"):
        T.init(jax.random.PRNGKey(0), tiny("mb_dscpp", shared_critic=False))
    with pytest.raises(ValueError, match="shared_critic"):
        tiny("mf_dscpp", shared_critic=1).validate()


def test_mf_dscpp_per_option_trains_evaluates_and_resumes_exactly(tmp_path):
    """DP subgoals (each option's critic scores its subgoals and its row of the table) and in-band
    evaluation on."""
    cfg = _E2E
    s0 = T.init(jax.random.PRNGKey(3), cfg)
    shared = jax.eval_shape(lambda: T.init(jax.random.PRNGKey(3), cfg.override(shared_critic=True)))
    assert shared.replay.data.option is None         # (traced only: no init program compiled)
    straight = s0
    for _ in range(4):
        straight, m = T.train_step(straight)
        assert all(np.isfinite(float(v)) for k, v in m.items() if k.startswith("td3/"))
    ran = np.unique(np.asarray(straight.replay.data.option)[np.asarray(straight.replay.valid)])
    # options take steps on their own new transitions; the global option (0) on all of them
    assert len(ran) >= 1 and 1 <= float(m["td3/options_learning"]) <= len(ran)
    assert float(m["td3/global_critic_loss"]) > 0
    free = np.asarray(straight.chain.status) == 0
    for o in range(cfg.chain.max_options):      # rows never created keep their initial networks
        if o not in ran and free[o]:
            assert_trees_equal(td3_option(straight.td3, o), td3_option(s0.td3, o))
    half = s0
    for _ in range(2):
        half, _ = T.train_step(half)
    ck.save_state(str(tmp_path), int(half.counters.iteration), half)
    resumed = ck.restore_state(str(tmp_path), T.init(jax.random.PRNGKey(99), cfg))
    assert_trees_equal(resumed, half)
    n_compiled = T.train_step._cache_size()
    for _ in range(2):
        resumed, _ = T.train_step(resumed)
    assert T.train_step._cache_size() == n_compiled
    assert_trees_equal(resumed, straight)
    summary, res = dscpp_jax.evaluate(straight, jax.random.PRNGKey(0), 2)
    assert 0.0 <= summary["eval/success_rate"] <= 1.0
    assert 0.0 <= float(m["inband/success_rate"]) <= 1.0
    policy = dscpp_jax.make_policy(straight)
    obs = straight.env_state.obs
    ex, acts, opts = jax.jit(policy.step)(policy.init(obs), obs, jax.random.PRNGKey(1))
    assert acts.shape == (obs.shape[0], 2) and np.all(np.isfinite(np.asarray(acts)))
    tcfg = TD3Config.from_section(straight.config.td3, straight.config.model_based)
    for i, o in enumerate(np.asarray(opts)):    # each env acted with its option's actor
        want = td3_act(tcfg, td3_option(straight.td3, o).actor_params, obs[i:i + 1],
                       ex.subgoal[i:i + 1])
        np.testing.assert_allclose(np.asarray(acts[i]), np.asarray(want[0]), rtol=1e-5, atol=1e-6)


def test_seed_group_with_per_option_critics():
    """Each run of a seed group updates its options as if alone (the actor-step predicate is
    reduced over both the seed and the option axis)."""
    cfg = _E2E     # train_step is compiled for it already when the test above ran
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    states = jax.vmap(lambda k: T.init(k, cfg))(keys)
    states, vm = jax.jit(T.train_step_group_impl)(states)
    one, m = T.train_step(T.init(keys[1], cfg))
    for a, b in zip(jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda x: x[1], states.td3)),
                    jax.tree_util.tree_leaves(one.td3)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-4)
    assert float(vm["td3/critic_loss"][1]) == pytest.approx(float(m["td3/critic_loss"]), rel=1e-4)

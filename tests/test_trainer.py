"""Trainer: config validation, no retracing, vmap over seeds, evaluation without side effects,
the policy constructor, NaN handling and every algorithm's train_step. The interpreted GPU
kernels inside train_step and the learning runs, which need XLA's full optimisation, are in
tests/test_learning.py."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscpp_jax
from dscpp_jax import acting as A
from dscpp_jax import trainer as T
from dscpp_jax.config import Config, preset
from dscpp_jax.td3 import TD3Config
from tests.trainer_fixtures import assert_trees_equal, tiny


def test_invalid_configs_fail_before_compiling():
    with pytest.raises(ValueError, match="choose one of"):
        Config(algo="ppo").validate()
    with pytest.raises(ValueError, match="raise replay_capacity"):
        preset("fast", "point_u_maze", "mf_dscpp", replay_capacity=100).validate()
    with pytest.raises(ValueError, match="max_options"):
        Config(max_options=2).validate()
    with pytest.raises(ValueError, match="td3_clip_targets needs discount < 1"):
        Config(td3_clip_targets=True, discount=1.0).validate()
    with pytest.raises(ValueError, match="td3_action_l2 must be >= 0"):
        Config(td3_action_l2=-0.5).validate()
    with pytest.raises(ValueError, match="td3_sample_block must be >= 1"):
        Config(td3_sample_block=0).validate()
    with pytest.raises(ValueError, match="ant_integrator must be Euler, RK4 or implicitfast"):
        Config(env="u_maze", ant_integrator="rk4").validate()
    with pytest.raises(ValueError, match="unknown config field"):
        Config().override(not_a_field=1)
    with pytest.raises(ValueError, match="valid names"):
        T.init(jax.random.PRNGKey(0), Config(env="no_such_maze"))


def test_presets_keep_paper_constants():
    p = preset("paper", "u_maze", "mb_dscpp")
    assert (p.chain.gestation, p.chain.buffer_len, p.chain.option_timeout, p.task.episode_length) == (10, 50, 200, 1000)
    assert (p.task.warmup_episodes, p.mpc.samples, p.mpc.horizon, p.run.num_envs) == (50, 14000, 7, 1)
    assert p.effective_td3_lr == 1e-5 and preset("paper", "u_maze", "mf_dscpp").effective_td3_lr == 3e-4
    hash(p)  # static jit argument
    assert TD3Config.from_section(p.td3, p.model_based).target_range is None  # the original does not clip TD targets
    assert TD3Config.from_section(p.override(td3_clip_targets=True).td3, p.override(td3_clip_targets=True).model_based).target_range == pytest.approx((-100.0, 0.0))
    assert TD3Config.from_section(p.override(td3_action_l2=1.0).td3, p.override(td3_action_l2=1.0).model_based).action_l2 == 1.0
    assert TD3Config.from_section(p.td3, p.model_based).action_l2 == 0.0                # off in the paper preset
    assert p.td3.sample_block == 1
    # the ant `fast` preset: the action penalty on the model-free actors only; blocked sampling
    for algo, l2 in (("mf_dscpp", 1.0), ("td3_her", 1.0), ("dsc", 0.0), ("mb_dscpp", 0.0)):
        f = preset("fast", "four_rooms", algo)
        assert (TD3Config.from_section(f.td3, f.model_based).action_l2, f.td3.sample_block) == (l2, 32), algo
    assert preset("fast", "point_u_maze", "mf_dscpp").td3.action_l2 == 0.0
    # bf16 in TD3's hidden layers for the ant's model-free learners; float32 elsewhere
    for algo, dt in (("mf_dscpp", "bfloat16"), ("td3_her", "bfloat16"), ("dsc", "bfloat16"),
                     ("mb_dscpp", "float32"), ("mb_flat", "float32")):
        assert TD3Config.from_section(preset("fast", "four_rooms", algo).td3, preset("fast", "four_rooms", algo).model_based).compute_dtype == dt, algo
    assert preset("fast", "point_u_maze", "mf_dscpp").td3.dtype == "float32"
    assert preset("paper", "u_maze", "mf_dscpp").td3.dtype == "float32"
    # MPC action sequences per decision: 2,048 on the ant U-maze, 4,096 on the other ant envs
    assert [preset("fast", e).mpc.samples for e in ("u_maze", "four_rooms", "medium", "large",
                                                      "ant_reacher")] == [2048] + [4096] * 4
    assert preset("fast", "point_u_maze").mpc.samples == 128
    # the chain's frontier: on for DSC++'s skill chains on the ant mazes with dead ends and on
    # four rooms, off elsewhere (the paper's baselines never have it)
    for env, algo, rows in (("medium", "mb_dscpp", 32), ("medium", "mf_dscpp", 32),
                            ("large", "mb_dscpp", 24),
                            ("four_rooms", "mb_dscpp", 24), ("four_rooms", "mf_dscpp", 24)):
        f = preset("fast", env, algo)
        assert (f.frontier.start_prob, f.frontier.parent, f.frontier.radius,
                f.frontier.inner_radius, f.chain.max_options) == (0.5, True, 6.0, 3.0, rows), (env, algo)
    # MB-DSC++ on the medium maze: the paper's one TD3 step per transition (0.25 elsewhere)
    assert [preset("fast", e, a).td3.updates_per_step for e, a in (
        ("medium", "mb_dscpp"), ("large", "mb_dscpp"), ("u_maze", "mb_dscpp"),
        ("medium", "mb_flat_value"), ("medium", "mf_dscpp"))] == [1.0, 0.25, 0.25, 0.25, 1.0]
    for env, algo in (("u_maze", "mb_dscpp"), ("four_rooms", "dual"), ("four_rooms", "td3_her"),
                      ("four_rooms", "dsc"), ("medium", "dsc"), ("medium", "dual"),
                      ("point_four_rooms", "mb_dscpp"), ("medium", "td3_her"),
                      ("medium", "mb_flat"), ("point_medium", "mb_dscpp")):
        f = preset("fast", env, algo)
        assert (f.frontier.start_prob, f.frontier.parent) == (0.0, False), (env, algo)
    assert preset("paper", "medium", "mb_dscpp").frontier.start_prob == 0.0
    # turning diverse starts off leaves the frontier off rather than failing validation
    f = preset("fast", "medium", "mb_dscpp", diverse_starts=False)
    assert (f.frontier.start_prob, f.frontier.parent) == (0.0, False)
    assert preset("fast", "medium", "mf_dscpp", frontier_start_prob=0.0).frontier.parent
    # the frontier's parameters count only where the frontier is on
    assert f.inert_fields() == {"frontier_radius", "frontier_inner_radius",
                                "frontier_candidates", "frontier_min_open", "frontier_goal_starts"}
    assert preset("fast", "medium", "mb_dscpp").inert_fields() == set()
    assert preset("fast", "medium", "mb_dscpp", frontier_start_prob=0.0).inert_fields() == {
        "frontier_inner_radius", "frontier_goal_starts"}
    # every preset of every env and algorithm is a valid config as it comes
    from dscpp_jax import envs
    from dscpp_jax.config import ALGOS
    for name in ("fast", "paper"):
        for env in envs.ENV_NAMES:
            for algo in ALGOS:
                preset(name, env, algo).validate()
    # the ant's integrator reaches the MuJoCo model; point-mass envs ignore it
    import mujoco
    assert T.make_env(p).mj_model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4   # D4RL's
    env = T.make_env(p.override(ant_integrator="Euler"))
    assert env.mj_model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert preset("fast", "u_maze").task.ant_integrator == "RK4"
    assert preset("fast", "four_rooms").task.ant_integrator == "RK4"
    assert preset("paper", "four_rooms").task.ant_integrator == "RK4"
    assert T.make_env(preset("fast", "point_u_maze", ant_integrator="RK4")).backend != "mjx"


def test_old_run_configs_with_removed_fields_still_load():
    # config.json of runs made before the upright / absorb switches left Config (off, as saved)
    cfg = preset("fast", "u_maze", "mf_dscpp", seed=3)
    old = dict(cfg.to_dict(), td3_upright_weight=0.0, td3_upright_min=0.5, td3_absorb_fallen=False,
               mpc_upright_weight=0.0, mpc_upright_min=0.5)
    assert Config.from_dict(old) == cfg
    assert "td3_absorb_fallen" not in Config().to_dict()


# tiny mb_dscpp with DP subgoals and warm-up: the no-retracing, policy and every-algorithm tests
# share its train_step and evaluate programs (each compile costs more than all their iterations)
MB_DP = tiny("mb_dscpp", subgoal="dp")


def test_no_retracing_across_iterations():
    cfg = MB_DP
    s = T.init(jax.random.PRNGKey(0), cfg)
    s, _ = T.train_step(s)
    n_train = T.train_step._cache_size()
    for _ in range(4):   # crosses the end of warm-up, chain growth and refits
        s, m = T.train_step(s)
    assert T.train_step._cache_size() == n_train
    from dscpp_jax.evaluate import evaluate_episodes
    dscpp_jax.evaluate(s, jax.random.PRNGKey(0), 2)
    n_eval = evaluate_episodes._cache_size()
    for i in range(2):
        s, _ = T.train_step(s)
        dscpp_jax.evaluate(s, jax.random.PRNGKey(i), 2)
    assert evaluate_episodes._cache_size() == n_eval
    assert T.train_step._cache_size() == n_train


def test_episodes_begun_after_the_warm_up_start_anywhere():
    # MB_DP: 4 envs, 100-step episodes, 20 steps per iteration, warm-up of 2 episodes. The four
    # first episodes (the warm-up, from the task start) all end on the last step of iteration 5;
    # the episodes begun there are past the warm-up and start at diverse free states
    cfg = MB_DP
    s = T.init(jax.random.PRNGKey(0), cfg)
    task_start = np.asarray(s.env_state.obs[:, :2])
    for _ in range(5):
        s, m = T.train_step(s)
    assert int(s.counters.episodes) == cfg.run.num_envs and float(m["train/warmup"]) == 1.0
    xy = np.asarray(s.env_state.obs[:, :2])
    assert np.all(np.linalg.norm(xy - task_start, axis=-1) > 1.0), (xy, task_start)


@pytest.mark.parametrize("prob", [1.0, 0.5])
def test_task_start_prob_starts_that_share_of_episodes_at_the_task_start(prob):
    # as above, with task_start_prob: after the warm-up, every episode (prob 1) or about half of
    # them (prob 0.5, 16 envs) begins at the task start (within the reset noise)
    cfg = tiny("mb_dscpp", subgoal="dp", task_start_prob=prob, num_envs=16)
    s = T.init(jax.random.PRNGKey(0), cfg)
    task_start = np.asarray(s.env_state.obs[:, :2])
    for _ in range(5):
        s, m = T.train_step(s)
    assert int(s.counters.episodes) == cfg.run.num_envs
    near = np.linalg.norm(np.asarray(s.env_state.obs[:, :2]) - task_start, axis=-1) < 0.5
    if prob == 1.0:
        assert near.all()
    else:
        assert 3 <= near.sum() <= 13, near


def test_vmap_over_seeds_equals_separate_runs():
    cfg = tiny("mf_dscpp")
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    states = jax.vmap(lambda k: T.init(k, cfg))(keys)
    vstep = jax.jit(jax.vmap(T.train_step_impl))
    for _ in range(3):
        states, vm = vstep(states)
    for i in range(2):
        s = T.init(keys[i], cfg)
        for _ in range(3):
            s, m = T.train_step(s)
        one = jax.tree_util.tree_map(lambda x: x[i], states)
        la, lb = jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(s)
        assert len(la) == len(lb)
        for a, b in zip(la, lb):
            np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                       rtol=1e-4, atol=1e-4)
        assert float(vm["counters/env_steps"][i]) == float(m["counters/env_steps"])


def test_evaluate_has_no_side_effects_and_takes_starts():
    cfg = tiny("mf_dscpp")
    s = T.init(jax.random.PRNGKey(1), cfg)
    s, _ = T.train_step(s)
    before = jax.tree_util.tree_map(np.asarray, s)
    summary, res = dscpp_jax.evaluate(s, jax.random.PRNGKey(0), 3)
    assert_trees_equal(before, s)
    assert res.xy.shape == (cfg.task.episode_length + 1, 3, 2) and res.option.shape == (cfg.task.episode_length, 3)
    assert 0.0 <= summary["eval/success_rate"] <= 1.0
    # failure bookkeeping: per-episode option failures add up to the per-option counts
    assert int(np.sum(res.option_failures)) == int(np.sum(res.option_executions)
                                                   - np.sum(res.option_successes))
    steps, glob = np.asarray(res.steps), np.asarray(res.global_steps)
    assert np.all((0 <= glob) & (glob <= steps))
    opt, act = np.asarray(res.option), np.asarray(res.active)
    np.testing.assert_array_equal(glob, ((opt == 0) & act).sum(0))
    assert summary["eval/global_option_share"] == pytest.approx(glob.sum() / steps.sum())
    np.testing.assert_array_equal(np.asarray(res.upright), 1.0)   # a point mass never tips
    assert summary["eval/flipped_rate"] == 0.0
    # a start inside the goal region succeeds at once
    goal = np.asarray(T.make_env(cfg).goal)
    summary, res = dscpp_jax.evaluate(s, starts=[goal + 0.1, [0.0, 0.0]])
    assert bool(res.success[0]) and int(res.steps[0]) == 1
    # deterministic: same key, same result
    a = dscpp_jax.evaluate(s, jax.random.PRNGKey(5), 3)[1]
    b = dscpp_jax.evaluate(s, jax.random.PRNGKey(5), 3)[1]
    np.testing.assert_array_equal(np.asarray(a.xy), np.asarray(b.xy))
    # with training's action noise: still read-only and repeatable, but other motions
    e1 = dscpp_jax.evaluate(s, jax.random.PRNGKey(5), 3, explore=True)[1]
    assert_trees_equal(before, s)
    e2 = dscpp_jax.evaluate(s, jax.random.PRNGKey(5), 3, explore=True)[1]
    np.testing.assert_array_equal(np.asarray(e1.xy), np.asarray(e2.xy))
    assert not np.allclose(np.asarray(e1.xy[1:]), np.asarray(a.xy[1:]))


def test_make_policy_runs_in_a_jitted_scan():
    cfg = MB_DP
    s = T.init(jax.random.PRNGKey(2), cfg)
    s, _ = T.train_step(s)
    env = T.make_env(cfg)
    policy = dscpp_jax.make_policy(s)

    @jax.jit
    def rollout(key):
        es = jax.vmap(env.reset)(jax.random.split(key, 3))
        carry = policy.init(es.obs)

        def body(c, k):
            es, pc = c
            pc, a, o = policy.step(pc, es.obs, k)
            return (jax.vmap(env.step)(es, a), pc), (es.obs[:, :2], o)
        _, (xy, opts) = jax.lax.scan(body, (es, carry), jax.random.split(key, 20))
        return xy, opts

    xy, opts = rollout(jax.random.PRNGKey(0))
    assert xy.shape == (20, 3, 2) and np.all(np.isfinite(np.asarray(xy)))
    assert np.all(np.asarray(opts) >= 0)


def test_options_time_out_after_exactly_option_timeout_steps():
    cfg = tiny("mf_dscpp")                      # option_timeout = 40
    s = T.init(jax.random.PRNGKey(3), cfg)
    env, B = T.make_env(cfg), cfg.run.num_envs
    far = jnp.full((B, 2), 100.0)              # never reached: only the timeout can end it
    xy = s.env_state.obs[:, :2]
    ex = s.exec.replace(option=jnp.zeros((B,), jnp.int32), subgoal=far,
                        opt_steps=jnp.zeros((B,), jnp.int32))

    @jax.jit
    def train_step_end(ex):
        ex = A.push_traj(ex, xy)               # training: one step taken, then the end test
        return ex, A.option_end(s.config, env, s.chain, ex, xy, jnp.zeros((B,)))[0]
    ends = []
    for _ in range(cfg.chain.option_timeout + 1):
        ex, ended = train_step_end(ex)
        ends.append(bool(ended.all()) if bool(ended.any()) else False)
    assert ends.index(True) == cfg.chain.option_timeout - 1   # ends right after step 40
    # the policy constructor counts the same way: 40 steps of one execution, then a new one
    policy = dscpp_jax.make_policy(s)
    pc = policy.init(s.env_state.obs)
    step = jax.jit(policy.step)
    counts = []
    for i in range(cfg.chain.option_timeout + 1):
        pc, _, _ = step(pc.replace(subgoal=jnp.where(pc.option[:, None] >= 0, far, pc.subgoal)),
                               s.env_state.obs, jax.random.PRNGKey(i))
        counts.append(int(pc.opt_steps[0]))
    assert counts == list(range(1, cfg.chain.option_timeout + 1)) + [1]


def test_nan_in_learning_stops_with_a_message(tmp_path):
    from dscpp_jax.host_loop import TrainingDiverged, train
    cfg = tiny("mf_dscpp")      # compiled above; TD3 updates (and the finite check) run in warm-up
    s = T.init(jax.random.PRNGKey(0), cfg)
    bad = s.replace(td3=s.td3.replace(critic_params=jax.tree_util.tree_map(
        lambda x: jnp.full_like(x, jnp.nan), s.td3.critic_params)))
    with pytest.raises(TrainingDiverged, match="TD3"):
        train(cfg, str(tmp_path / "run"), progress=False, initial_state=bad)
    from dscpp_jax import checkpoint as ck
    assert ck.latest_step(str(tmp_path / "run")) == 0


def test_a_full_table_without_the_start_warns_once(tmp_path, capsys):
    """A full option table whose regions no longer hold the start cannot grow the link it needs:
    the run says so once, with the fix, and goes on."""
    from dscpp_jax.host_loop import stuck_chain_warning, train
    cfg = tiny("mf_dscpp")      # compiled above
    assert stuck_chain_warning({"options/capacity_hit": 1.0, "options/start_covered": 1.0}, cfg) is None
    assert stuck_chain_warning({"options/capacity_hit": 0.0, "options/start_covered": 0.0}, cfg) is None
    assert stuck_chain_warning({"train/episode_success": 0.0}, cfg) is None   # flat algorithms
    msg = stuck_chain_warning({"options/capacity_hit": 1.0, "options/start_covered": 0.0}, cfg)
    assert "max_options=4" in msg and "--set max_options=12" in msg
    s = T.init(jax.random.PRNGKey(0), cfg)
    full = s.replace(chain=s.chain.replace(capacity_hit=jnp.asarray(True)))   # nothing covers the start
    train(cfg, str(tmp_path / "run"), progress=False, initial_state=full, max_iterations=2)
    err = capsys.readouterr().err
    assert err.count("the option table is full") == 1 and "iteration 1:" in err


def test_a_stalled_link_warns_once(tmp_path, capsys):
    """A link in gestation that has failed 1,000 executions without a success stops the chain:
    the run says so once, naming the option it targets, and goes on."""
    from dscpp_jax.host_loop import stalled_link_warning, train
    from dscpp_jax.options import GESTATION
    cfg = tiny("mf_dscpp")      # compiled above
    base = {"options/gestation_executions": 1000.0, "options/gestation_successes": 0.0,
            "options/gestation_parent": 3.0}
    assert "targets option 3" in stalled_link_warning(base, cfg)
    assert "1000 executions" in stalled_link_warning(base, cfg)
    assert stalled_link_warning({**base, "options/gestation_successes": 1.0}, cfg) is None
    assert stalled_link_warning({**base, "options/gestation_executions": 999.0}, cfg) is None
    assert stalled_link_warning({"train/episode_success": 0.0}, cfg) is None   # flat algorithms
    s = T.init(jax.random.PRNGKey(0), cfg)
    ch = s.chain
    stalled = ch.replace(status=ch.status.at[2].set(GESTATION), parent=ch.parent.at[2].set(1),
                         executions=ch.executions.at[2].set(1500))
    train(cfg, str(tmp_path / "run"), progress=False, initial_state=s.replace(chain=stalled),
          max_iterations=2)
    err = capsys.readouterr().err
    assert err.count("has failed 1500 executions") == 1 and "targets option 1" in err
    assert "iteration 1:" in err


@pytest.mark.parametrize("algo,subgoal", [("td3_her", "robust"), ("mb_flat", "robust"),
                                          ("mb_flat_value", "robust"), ("dsc", "robust"),
                                          ("mb_dscpp", "dp")])
def test_every_algorithm_trains_and_evaluates(algo, subgoal):
    cfg = tiny(algo, subgoal=subgoal)     # mb_dscpp/dp: MB_DP, compiled by the tests above
    s = T.init(jax.random.PRNGKey(0), cfg)
    for _ in range(7):                     # warm-up ends in iteration 5; two iterations after it
        s, m = T.train_step(s)
    assert float(m["train/warmup"]) == 0.0
    assert all(np.isfinite(v) for k, v in m.items() if k.startswith(("td3/", "dynamics/")))
    assert (s.dyn is not None) == cfg.model_based and (s.chain is not None) == cfg.hierarchical
    summary, res = dscpp_jax.evaluate(s, jax.random.PRNGKey(0), 2)
    assert 0.0 <= summary["eval/success_rate"] <= 1.0
    if not cfg.hierarchical:
        assert np.all(np.asarray(res.option)[np.asarray(res.active)] == 0)   # global option only


# a tiny MB-DSC++ on the ant U-maze (MJX, 2 envs x 3 steps): the NaN-physics and fallen-ant
# tests share its train_step program (an ant compile costs more than both tests' steps)
ANT_TINY = dict(num_envs=2, steps_per_iter=3, warmup_episodes=0, ant_integrator="Euler",
                episode_length=50, max_options=4, max_pos_traj=4, max_neg=4, buffer_len=10,
                option_timeout=20, td3_hidden=16, td3_batch_size=8, replay_capacity=100,
                model_capacity=100, dyn_hidden=16, dyn_batch_size=8, dyn_pretrain_steps=1,
                mpc_samples=8, mpc_horizon=2, mpc_dtype="float32", eval_every=0,
                inband_eval_envs=0)


def test_nan_physics_ends_that_episode_and_stays_out_of_learning():
    # ant U-maze (MJX, few steps): one environment's physics state is corrupted with NaN
    cfg = preset("fast", "u_maze", "mb_dscpp", **ANT_TINY)
    s = T.init(jax.random.PRNGKey(0), cfg)
    d = s.env_state.pipeline_state
    bad = s.replace(env_state=s.env_state.replace(
        pipeline_state=d.replace(qvel=d.qvel.at[0, 6].set(jnp.nan))))
    s2, m = T.train_step(bad)
    assert float(m["train/nan_physics_steps"]) == 1.0
    assert int(s2.counters.episodes) == 1                      # that episode ended (and restarted)
    assert np.all(np.isfinite(np.asarray(s2.env_state.obs)))
    assert np.all(np.isfinite(np.asarray(s2.env_state.pipeline_state.qvel)))
    for buf in (s2.replay, s2.model_replay):
        valid = np.asarray(buf.valid)
        assert valid.sum() == cfg.run.num_envs * cfg.run.steps_per_iter - 1   # the NaN step was not stored
        for leaf in jax.tree_util.tree_leaves(buf.data):
            x = np.asarray(leaf)
            if np.issubdtype(x.dtype, np.floating):
                assert np.all(np.isfinite(x[valid]))
    assert all(np.isfinite(v) for k, v in m.items() if k.startswith(("td3/", "dynamics/")))


def test_task_start_prob_outside_0_1_is_refused():
    with pytest.raises(ValueError, match="task_start_prob"):
        tiny("mf_dscpp", task_start_prob=1.5).validate()


def test_on_back_share_counts_the_steps_of_a_fallen_ant():
    # ant U-maze (MJX, few steps): environment 0 starts on its back and stays there, as in the
    # paper (a fall does not end the episode); train/on_back_share counts its steps
    cfg = preset("fast", "u_maze", "mb_dscpp", **ANT_TINY)   # compiled by the NaN test above
    s = T.init(jax.random.PRNGKey(0), cfg)
    env = T.make_env(cfg)
    d = s.env_state.pipeline_state
    on_back = jnp.asarray([0.0, 1.0, 0.0, 0.0])      # half a turn about x: the torso's z points down
    s = s.replace(env_state=s.env_state.replace(
        pipeline_state=d.replace(qpos=d.qpos.at[0, 3:7].set(on_back))))
    s2, m = T.train_step(s)
    assert float(m["train/on_back_share"]) == 0.5          # env 0's three steps of six
    assert int(s2.counters.episodes) == 0
    up = np.asarray(env.upright(s2.env_state.obs))
    assert up[0] < 0 and up[1] > 0.5
    assert np.all(np.isfinite(np.asarray(s2.env_state.obs)))

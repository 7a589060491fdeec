"""In-band evaluation (`Config.eval.inband_envs`): evaluation episodes stepped inside
`train_step` never touch learning state, report what `evaluate` reports for the same policy,
checkpoint and resume exactly, work in seed groups, and compile once."""
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import checkpoint as ck
from dscpp_jax import acting as A
from dscpp_jax import trainer as T
from dscpp_jax.config import Config
from dscpp_jax.evaluate import evaluate_episodes
from tests.trainer_fixtures import TINY, assert_trees_equal, tiny

E = 3
ITERS = 7   # 4 envs x 20 steps, 100-step episodes: warm-up ends in iteration 5
# td3_her with in-band envs: the checkpoint, seed-group, command-line and physics-path tests
# share its train_step and group programs (each compile costs more than their iterations)
TD3_INBAND = dict(inband_eval_envs=E, inband_eval_window=5, steps_per_iter=40)


def _run(cfg, iters, seed=0):
    s = T.init(jax.random.PRNGKey(seed), cfg)
    ms, sizes = [], []
    for _ in range(iters):
        s, m = T.train_step(s)
        ms.append(jax.device_get(m))
        sizes.append(T.train_step._cache_size())
    return s, ms, sizes


@pytest.fixture(scope="module")
def mb_runs():
    """mb_dscpp (options, subgoals, MPC with random samples) without and with in-band envs."""
    cfg = tiny("mb_dscpp")
    off = _run(cfg, ITERS)
    on = _run(cfg.override(inband_eval_envs=E), ITERS)
    return cfg, off, on


def test_config_field_is_validated():
    with pytest.raises(ValueError, match="inband_eval_envs=-1 must be >= 0"):
        Config(inband_eval_envs=-1).validate()
    with pytest.raises(ValueError, match="inband_eval_window=-2 must be >= 0"):
        Config(inband_eval_window=-2).validate()
    assert Config(inband_eval_envs=8).inband_window == 8
    assert Config(inband_eval_envs=8, inband_eval_window=32).inband_window == 32


def test_inband_never_touches_learning_state(mb_runs):
    """Same seed with and without in-band envs: every leaf of the learning state (env states,
    option executions, chain and classifiers, TD3, dynamics, replay buffers, DP table, counters,
    the PRNG key) and every training metric are bitwise equal."""
    cfg, (s_off, m_off, _), (s_on, m_on, _) = mb_runs
    assert s_off.inband is None and s_on.inband is not None
    assert_trees_equal(s_off, s_on.replace(inband=None, config=s_off.config))
    assert float(m_on[-1]["train/warmup"]) == 0.0 and float(m_on[-1]["td3/critic_loss"]) != 0.0
    for a, b in zip(m_off, m_on):
        assert set(b) - set(a) == {"inband/success_rate", "inband/steps_to_goal",
                                   "inband/episodes", "inband/window"}
        for k in a:
            np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]), err_msg=k)
        for k in ("inband/success_rate", "inband/steps_to_goal", "inband/episodes"):
            assert np.isfinite(b[k]), k
    ib = s_on.inband
    steps = cfg.run.steps_per_iter * ITERS
    assert int(ib.t) == steps
    assert int(ib.episodes) >= E * (steps // cfg.task.episode_length)   # episodes end by the limit
    assert float(m_on[-1]["inband/episodes"]) == int(ib.episodes)


def test_no_retracing_with_inband(mb_runs):
    _, _, (_, _, sizes) = mb_runs
    assert sizes[1:] == [sizes[0]] * (len(sizes) - 1)   # warm-up ends, episodes restart


def test_metrics_convention_before_and_after_episodes():
    cfg = tiny("td3_her", inband_eval_envs=2, inband_eval_window=3)
    ib = T.inband_init(jax.random.PRNGKey(0), cfg)
    m = T.inband_metrics(cfg, ib)
    assert {k: float(v) for k, v in m.items()} == {
        "inband/success_rate": 0.0, "inband/steps_to_goal": float(cfg.task.episode_length),
        "inband/episodes": 0.0, "inband/window": 0.0}
    # a ring of 3 after 5 episodes holds the last 3 (slots 0, 1 rewritten by episodes 4, 5)
    ib = ib.replace(success=jnp.array([True, False, True]), steps=jnp.array([10, 100, 30]),
                    episodes=jnp.asarray(5, jnp.int32))
    m = {k: float(v) for k, v in T.inband_metrics(cfg, ib).items()}
    assert m == {"inband/success_rate": pytest.approx(2 / 3), "inband/steps_to_goal": 20.0,
                 "inband/episodes": 5.0, "inband/window": 3.0}


def test_inband_steps_follow_evaluate_inside_train_step(mb_runs):
    """A learned state (past warm-up, a grown chain) with its in-band envs restarted at the task
    start with key k: the in-band envs of the next train_step move exactly as the episodes of
    `evaluate_episodes(state, k, E)` (same resets, same option and subgoal keys, same MPC samples:
    in-band step t acts with fold_in(k_run, t) as evaluation's step t does), since they act with
    the policy of the iteration's start."""
    cfg, _, (s_on, _, _) = mb_runs
    k = jax.random.PRNGKey(42)
    s = s_on.replace(inband=T.inband_init(k, s_on.config))
    res = evaluate_episodes(s, k, E)
    s2, m = T.train_step(s)          # the program compiled for the fixture
    ib, T_ = s2.inband, cfg.run.steps_per_iter
    assert np.all(np.asarray(res.steps) > T_) and int(ib.episodes) == 0
    np.testing.assert_array_equal(np.asarray(ib.env_state.obs[:, :2]), np.asarray(res.xy[T_]))
    np.testing.assert_array_equal(np.asarray(ib.ep_steps), T_)
    # learning went on as without in-band envs
    s_plain, _ = T.train_step(s.replace(inband=None, config=s_on.config.override(
        inband_eval_envs=0).device_view()))
    assert_trees_equal(s_plain.td3, s2.td3)


def test_inband_episodes_equal_evaluate_episodes(mb_runs):
    """The in-band act / step / record functions scanned over one episode length on a fixed state
    reproduce `evaluate_episodes`' episodes: positions step by step until each ends, then its success
    and length; the ring and metrics hold the finished episodes in order of finishing. A wide goal
    tolerance makes some episodes succeed, at different lengths, and restart."""
    _, _, (s_on, _, _) = mb_runs
    # the task start is about 8 from the goal: at 7.8 most of the 6 episodes succeed within a few
    # to ~20 steps and restart, and one runs to the limit (checked below)
    cfg = s_on.config.override(goal_tolerance=7.8, inband_eval_envs=6, inband_eval_window=4)
    s = s_on.replace(config=cfg)
    env = T.inband_env(cfg)
    k = jax.random.PRNGKey(7)
    n = cfg.eval.inband_envs
    res = evaluate_episodes(s, k, n)

    @jax.jit
    def roll(ib):
        def body(ib, _):
            ex, acts = A.inband_act(cfg, env, s.chain, s.dp_table, s.td3, s.dyn, ib)
            nes = jax.vmap(env.step)(ib.env_state, acts)
            out = (nes.obs[:, :2], nes.done > 0, nes.info["success"] > 0)
            return A.inband_record(cfg, env, s.chain, ib, ex, nes), out
        return jax.lax.scan(body, ib, None, length=cfg.task.episode_length)

    ib, (xy, done, succ) = jax.device_get(roll(T.inband_init(k, cfg)))
    steps, success = np.asarray(res.steps), np.asarray(res.success)
    assert success.any() and not success.all() and len(set(steps[success])) > 1
    for i in range(n):
        L = steps[i]
        np.testing.assert_array_equal(xy[:L, i], np.asarray(res.xy)[1:L + 1, i])
        assert done[L - 1, i] and not done[:L - 1, i].any()
        assert succ[L - 1, i] == success[i]
    # every finished episode, in order of finishing (step, then env): its success and length
    fin, start = [], np.zeros(n, int)
    for t in range(cfg.task.episode_length):
        for i in np.flatnonzero(done[t]):
            fin.append((succ[t, i], t + 1 - start[i]))
            start[i] = t + 1
    assert int(ib.episodes) == len(fin) >= n
    last = fin[-cfg.inband_window:]
    m = T.inband_metrics(cfg, ib)
    assert float(m["inband/success_rate"]) == pytest.approx(np.mean([a for a, _ in last]))
    assert sorted(zip(np.asarray(ib.success).tolist(), np.asarray(ib.steps).tolist())) == \
        sorted((bool(a), int(b)) for a, b in last)


def test_checkpoint_resume_continues_exactly(tmp_path):
    cfg = tiny("td3_her", **TD3_INBAND)
    s = T.init(jax.random.PRNGKey(3), cfg)
    for _ in range(2):
        s, _ = T.train_step(s)
    ck.save_state(str(tmp_path), 2, s)
    a = s
    for _ in range(3):
        a, ma = T.train_step(a)
    like = T.init(jax.random.PRNGKey(99), cfg)
    b = ck.restore_state(str(tmp_path), like)
    assert_trees_equal(b, s)
    for _ in range(3):
        b, mb = T.train_step(b)
    assert_trees_equal(a, b)
    assert int(a.inband.episodes) > 0
    for k in ma:
        np.testing.assert_array_equal(np.asarray(ma[k]), np.asarray(mb[k]), err_msg=k)


def test_state_without_inband_has_the_leaves_of_before():
    """Off, the TrainState's `inband` is None: no leaf, so checkpoints keep their layout."""
    cfg = tiny("td3_her")
    shapes = jax.eval_shape(lambda k: T.init_impl(k, cfg), jax.random.PRNGKey(0))
    assert shapes.inband is None
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(shapes)[0]]
    assert not any("inband" in p for p in paths)
    on = jax.eval_shape(lambda k: T.init_impl(k, cfg.override(inband_eval_envs=2)),
                        jax.random.PRNGKey(0))
    assert on.inband.success.shape == (2,) and on.inband.env_state.obs.shape[0] == 2


def test_seed_group_with_inband_equals_separate_runs(tmp_path):
    """Two seeds in one group program (vmapped, seed axis named) with in-band envs: each seed's
    in-band state and metrics equal its separate run (floats to the seed-group tolerance, counts
    exactly); a seed marked inactive keeps its in-band state."""
    from dscpp_jax import seed_group as SG
    cfg = tiny("td3_her", **TD3_INBAND)
    g = SG.init_group([0, 1], cfg)
    gm = []
    for _ in range(3):
        g, m = SG.train_step_group(g)
        gm.append(SG.to_host(m))
    for i in (0, 1):
        s = T.init(jax.random.PRNGKey(i), cfg)
        for it in range(3):
            s, m = T.train_step(s)
            for k, v in m.items():
                exact = k.startswith(("counters/", "inband/episodes", "inband/window"))
                np.testing.assert_allclose(gm[it][k][i], np.asarray(v), rtol=0 if exact else 1e-4,
                                           atol=0 if exact else 1e-5, equal_nan=True, err_msg=k)
        one = SG.seed_state(g, i).inband
        for name in ("t", "ep_steps", "success", "steps", "episodes"):
            np.testing.assert_array_equal(np.asarray(getattr(one, name)),
                                          np.asarray(getattr(s.inband, name)), err_msg=name)
        np.testing.assert_allclose(np.asarray(one.env_state.obs), np.asarray(s.inband.env_state.obs),
                                   rtol=1e-4, atol=1e-5)
    assert int(SG.seed_state(g, 0).inband.episodes) > 0
    before = SG.seed_state(g, 1).inband
    g, _ = SG.train_step_group(g, active=np.array([True, False]))
    assert_trees_equal(SG.seed_state(g, 1).inband, before)
    # the group checkpoint holds the in-band state
    gc = SG.GroupCheckpointer(str(tmp_path))
    gc.save(4, g)
    back = gc.restore(SG.init_group([0, 1], cfg))
    gc.close()
    assert_trees_equal(SG.to_host(back), SG.to_host(g))


def test_checkpoints_written_before_the_inband_field_restore(tmp_path):
    """A checkpoint in the layout of a TrainState without the `inband` field (what versions before
    in-band evaluation wrote) restores into a state with in-band evaluation off."""
    import dataclasses

    import flax.struct
    import orbax.checkpoint as ocp
    cfg = tiny("td3_her")
    s = T.init(jax.random.PRNGKey(0), cfg)
    names = [f.name for f in dataclasses.fields(s) if f.name not in ("config", "inband")]
    Old = flax.struct.dataclass(type("TrainState", (), {"__annotations__": {n: object for n in names}}))
    old = Old(**{n: getattr(s, n) for n in names})
    mgr = ocp.CheckpointManager(str(tmp_path / ck.CKPT_DIR),
                                options=ocp.CheckpointManagerOptions(create=True))
    mgr.save(4, args=ocp.args.StandardSave(ck.to_storable(old)))
    mgr.wait_until_finished()
    mgr.close()
    back = ck.restore_state(str(tmp_path), T.init(jax.random.PRNGKey(9), cfg))
    assert back.inband is None
    assert_trees_equal(back, s)


def test_cli_logs_inband_metrics(tmp_path, capsys):
    """`--set inband_eval_envs=3`: metrics.csv has the inband/* columns every iteration and the
    per-evaluation line shows the in-band success."""
    from dscpp_jax.cli import main
    from dscpp_jax.run_logging import read_metrics
    run = str(tmp_path / "run")
    args = ["train", "--env", "point_u_maze", "--algo", "td3_her", "--total-steps", "480",
            "--eval-every", "3", "--no-progress"]
    host = ("total_env_steps", "eval_every", "checkpoint_every")    # given as flags above
    for k, v in {**TINY, **TD3_INBAND}.items():   # the config of the tests above: compiled
        if k not in host:
            args += ["--set", f"{k}={v}"]
    assert main(args + ["--run-dir", run]) == 0
    m = read_metrics(run)
    assert len(m["iteration"]) == 3
    assert m["inband/episodes"] == [0.0, 0.0, float(E)]   # each in-band env's first episode
    assert all(np.isfinite(m["inband/success_rate"]))
    assert "inband_success" in capsys.readouterr().out
    # a seed group through the command line: each seed's metrics.csv has them too
    group = str(tmp_path / "group")
    assert main(args + ["--run-dir", group, "--seeds", "0-1"]) == 0
    for s in (0, 1):
        g = read_metrics(f"{group}/s{s}")
        assert g["inband/episodes"] == [0.0, 0.0, float(E)]
    out = capsys.readouterr().out
    assert "inband_success mean" in out
    assert "episodes/seed " in out          # per seed (min-max), as env_steps/seed beside it
    # the curves draw in-band success only from iterations where an in-band episode had finished
    from dscpp_jax import plots
    x, y = plots.metric_curve(run, "inband/success_rate", "iteration")
    assert x.tolist() == [3.0] and y.tolist() == m["inband/success_rate"][2:]
    out = str(tmp_path / "plots")
    assert main(["plot", "--curves-only", run, f"{group}/s0", f"{group}/s1", "--out", out]) == 0
    assert os.path.getsize(os.path.join(out, "curves.png")) > 10_000


def test_second_physics_step_path_equals_the_batched_one():
    """`inband_eval_batched=False` (the path MuJoCo Warp always takes): the in-band envs step
    separately; learning state is bitwise that of a run without them, and on the point mass (whose
    step is per env) the in-band state is that of the batched path."""
    cfg = tiny("td3_her", steps_per_iter=40)
    off, _, _ = _run(cfg, 3)
    on = tiny("td3_her", **TD3_INBAND)           # the batched path's program: compiled above
    sep, m_sep, _ = _run(on.override(inband_eval_batched=False), 3)
    bat, m_bat, _ = _run(on, 3)
    assert not T.inband_batched(sep.config) and T.inband_batched(bat.config)
    assert_trees_equal(off, sep.replace(inband=None, config=off.config))
    assert_trees_equal(sep.inband, bat.inband)
    assert int(sep.inband.episodes) > 0
    for k in m_bat[-1]:
        np.testing.assert_array_equal(np.asarray(m_sep[-1][k]), np.asarray(m_bat[-1][k]), err_msg=k)


def test_warp_inband_envs_share_the_training_physics_batch():
    """On MuJoCo Warp the in-band envs join the training envs in one physics batch
    (`envs.goal_env.join_states`: per-world arrays and the contact buffers shared by a batch's
    worlds concatenated, split again after the step). Each world steps alone on Warp, so training
    state, in-band state and metrics equal those of the path with a second physics step; in a
    two-seed group each seed matches its separate run."""
    from dscpp_jax.envs.ant_maze import warp_available
    if not warp_available():
        pytest.skip("warp-lang is not installed")
    from dscpp_jax import seed_group as SG
    from dscpp_jax.config import preset
    cfg = preset("fast", "u_maze", "td3_her", physics="warp", num_envs=2, steps_per_iter=12,
                 episode_length=5, warmup_episodes=0, td3_hidden=16, td3_batch_size=16,
                 td3_updates_per_step=0.1, replay_capacity=500, eval_episodes=1,
                 inband_eval_envs=2)
    sep, m_sep, _ = _run(cfg.override(inband_eval_batched=False), 1)
    bat, m_bat, _ = _run(cfg, 1)
    assert int(bat.inband.episodes) == 4   # two 5-step episodes per in-band env finished
    # everything but the contact scratch that every step rewrites: the buffers shared by a
    # batch's worlds (their split halves hold the contacts in the joint batch's order) and each
    # constraint's index into them (`efc__id`)
    scratch = ("contact__", "nacon", "ncollision", "efc__id")
    def per_world(state):
        paths = jax.tree_util.tree_leaves_with_path(ck.to_storable(state))
        return {jax.tree_util.keystr(p): x for p, x in paths
                if not any(n in jax.tree_util.keystr(p) for n in scratch)}
    a, b = per_world(sep.replace(config=bat.config)), per_world(bat)
    assert a.keys() == b.keys() and len(a) > 100
    differ = [k for k in a if not np.array_equal(np.asarray(a[k]), np.asarray(b[k]))]
    assert differ == [], differ
    for k in m_bat[-1]:
        np.testing.assert_array_equal(np.asarray(m_sep[-1][k]), np.asarray(m_bat[-1][k]), err_msg=k)
    states, _ = SG.train_step_group(SG.init_group([0, 1], cfg))
    for i in (0, 1):   # seed 0's separate run is `bat` (the same init and step)
        one = bat if i == 0 else T.train_step(T.init(jax.random.PRNGKey(i), cfg))[0]
        got = SG.seed_state(states, i)
        for a, b in ((got.td3, one.td3), (got.inband.success, one.inband.success),
                     (got.inband.env_state.obs, one.inband.env_state.obs),
                     (got.env_state.obs, one.env_state.obs)):
            for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
                np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-3, atol=1e-4)

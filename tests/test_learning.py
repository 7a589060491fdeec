"""The trainer at XLA's full optimisation (`tests/run_files.py`): the interpreted fused GPU kernels
inside `train_step` against XLA's path, and real learning on the point-mass mazes.

The kernel test compares the chain that the interpreted SMO kernel fits with XLA's loop's to
1e-5, which XLA's lowest optimisation level rounds apart; the learning runs execute more than they
compile (about a third less CPU time at full optimisation). Every other trainer test is in
tests/test_trainer.py, which compiles without XLA's expensive passes."""
import re

import jax
import numpy as np
import pytest

import dscpp_jax
from dscpp_jax import trainer as T
from dscpp_jax.config import preset
from tests.trainer_fixtures import background_jobs, tiny, worker_on_spare_cores


def _scripted_goal_option_outcomes(s):
    """Four successes and four failures of the goal option recorded into a fresh chain."""
    from dscpp_jax import options as O
    cfg, B = s.config, 8
    rng = np.random.default_rng(0)
    goal = np.asarray(T.make_env(cfg).goal, np.float32)
    succ = np.arange(B) < 4
    start = np.where(succ[:, None], goal + rng.uniform(-1, 1, (B, 2)), rng.uniform(-1, 1, (B, 2)))
    traj = goal + rng.uniform(-1, 1, (B, cfg.chain.buffer_len, 2))
    obs = np.zeros((B, T.observation_size(cfg)), np.float32)
    obs[:, :2] = start
    return O.record_outcomes(s.chain, np.full((B,), O.GOAL, np.int32), succ,
                             start.astype(np.float32), traj.astype(np.float32),
                             np.ones((B, cfg.chain.buffer_len), bool), np.ones((B,), bool),
                             start_obs=obs)


def test_gpu_kernels_inside_train_step_interpreted():
    # The fused SMO kernel (svm_backend="pallas") and the fused MPC kernel with the value net
    # inside (mpc_backend="pallas") wired through train_step and evaluate, run in Pallas interpret
    # mode on the CPU. The SMO kernel takes the XLA loop's path: the same chain comes out.
    # Trained: XLA vs Pallas SMO, both with the fused MPC kernel (each compile here costs ~15 s);
    # the XLA MPC (every other test's) is traced only, to see that no kernel is in its program.
    base = dict(warmup_episodes=0, gestation=1, mpc_dtype="bfloat16", mpc_samples=16)

    def kernels(state):
        return set(re.findall(r"name=(\w+)", str(jax.make_jaxpr(T.train_step_impl)(state))))
    cfg = tiny("mb_dscpp", svm_backend="pallas", mpc_backend="xla", **base)
    names = kernels(jax.eval_shape(lambda: T.init(jax.random.PRNGKey(4), cfg)))
    assert "smo" in names and "mpc_rollout" not in names
    states = {}
    for svm_backend, mpc_backend in (("xla", "pallas"), ("pallas", "pallas")):
        cfg = tiny("mb_dscpp", svm_backend=svm_backend, mpc_backend=mpc_backend, **base)
        s = T.init(jax.random.PRNGKey(4), cfg)
        s = s.replace(chain=_scripted_goal_option_outcomes(s))   # something for the refits
        names = kernels(s)
        assert ("smo" in names) == (svm_backend == "pallas")          # the kernels are really used
        assert ("mpc_rollout" in names) == (mpc_backend == "pallas")
        for _ in range(3):
            s, m = T.train_step(s)
        assert all(np.isfinite(v) for k, v in m.items() if k.startswith(("td3/", "dynamics/")))
        summary, _ = dscpp_jax.evaluate(s, jax.random.PRNGKey(0), 2)
        assert 0.0 <= summary["eval/success_rate"] <= 1.0
        states[svm_backend, mpc_backend] = s
    a, b = states["xla", "pallas"].chain, states["pallas", "pallas"].chain
    assert bool(a.fitted[1:].any())                  # classifiers were really refit
    np.testing.assert_array_equal(np.asarray(a.fitted), np.asarray(b.fitted))
    for x, y in zip(jax.tree_util.tree_leaves(a.clf), jax.tree_util.tree_leaves(b.clf)):
        np.testing.assert_allclose(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                   rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="mpc_dtype=bfloat16"):
        tiny("mb_dscpp", mpc_backend="pallas").validate()


# ------------------------------------------------------------------------------------------------
# The learning runs (about three minutes of compiling and training between them) run in a worker
# process that starts with this module, beside the kernel test above (compiling, on one core
# mostly); their tests below wait for the results and check them here.
# ------------------------------------------------------------------------------------------------
def _learn_until(algo, max_iters, seed=0, env="point_u_maze", **kw):
    """Train a point-mass maze with the CPU preset; evaluate every 4 iterations; stop at the
    first evaluation with >= 80 % success from the task start. Returns (best summary, state)."""
    cfg = preset("fast", env, algo, seed=seed, **kw)
    s = T.init(jax.random.PRNGKey(seed), cfg)
    summary = {"eval/success_rate": 0.0}
    for i in range(1, max_iters + 1):
        s, m = T.train_step(s)
        if i >= 8 and i % 4 == 0:
            summary, _ = dscpp_jax.evaluate(s, jax.random.PRNGKey(i), 8)
            if summary["eval/success_rate"] >= 0.8:
                break
    return summary, s, m


def _learn_job(algo, max_iters, env="point_u_maze"):
    summary, s, _ = _learn_until(algo, max_iters, env=env)
    return summary, int(s.counters.env_steps), int(s.chain.num_options)


# dsc (the paper's baseline: one TD3 per option on the observation alone) on the point U-maze.
# Its evaluations from the route starts swing between checks, and the iteration where it first
# crosses a level moves by tens of iterations from one CPU model to another (the same program,
# compiled for another instruction set, rounds differently): the bar is half of the starts, the
# budget three checks past the slowest crossing measured.
DSC_LEARN_ITERS = 96
DSC_LEARN_THRESHOLD = 0.5
# Starts along the U's route to the goal, 2 to 16 units of path from it (the task start is 24):
# the second and third corridors that the chain's options cover first.
ROUTE_STARTS = np.array([[2, 8], [4, 8], [6, 8], [8, 8], [8, 6], [8, 4], [8, 2], [8, 0]],
                        np.float32)


def _baseline_learn_job(algo):
    """The fast preset on the point U-maze with 200-step episodes (more episode starts, which a
    learner without hindsight relabelling needs to find its sparse reward); every 4 iterations
    from the 16th, evaluate deterministically from ROUTE_STARTS; stop at the first evaluation
    with >= DSC_LEARN_THRESHOLD success. Returns (best success, env steps, options in the chain,
    training episodes' success in the last iteration)."""
    cfg = preset("fast", "point_u_maze", algo, seed=0, episode_length=200)
    s = T.init(jax.random.PRNGKey(0), cfg)
    best, m = 0.0, {}
    for i in range(1, DSC_LEARN_ITERS + 1):
        s, m = T.train_step(s)
        if i >= 16 and i % 4 == 0:
            summary, _ = dscpp_jax.evaluate(s, jax.random.PRNGKey(i), starts=ROUTE_STARTS)
            best = max(best, summary["eval/success_rate"])
            if best >= DSC_LEARN_THRESHOLD:
                break
    return best, int(s.counters.env_steps), int(s.chain.num_options), \
        float(m["train/episode_success"])


_JOBS = {   # test (node name) -> (function, arguments); the longest first
    "test_mb_dscpp_learns_point_four_rooms": (_learn_job, ("mb_dscpp", 48, "point_four_rooms")),
    "test_dscpp_learns_point_u_maze[mb_dscpp]": (_learn_job, ("mb_dscpp", 40)),
    "test_baselines_learn_point_u_maze[dsc]": (_baseline_learn_job, ("dsc",)),
    "test_dscpp_learns_point_u_maze[mf_dscpp]": (_learn_job, ("mf_dscpp", 40)),
}


@pytest.fixture(scope="module", autouse=True)
def background(request, tmp_path_factory):
    """Starts the jobs of the selected tests in one worker process beside this one before the
    first test of this module runs; {test name: future}."""
    yield from background_jobs(request, tmp_path_factory, _JOBS, workers=1,
                               setup=worker_on_spare_cores)


def _result(background, request):
    """The test's job result from the worker (run here if it was not started there)."""
    name = request.node.name
    if name not in background:
        fn, args = _JOBS[name]
        return fn(*args)
    return background[name].result(timeout=1800)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["mb_dscpp", "mf_dscpp"])
def test_dscpp_learns_point_u_maze(algo, background, request):
    # budget: at most 40 iterations x 1,600 env steps = 64k env steps (the runs we measured
    # reached 100 % eval success after 32k (MB) and ~40k (MF) steps)
    summary, env_steps, num_options = _result(background, request)
    assert summary["eval/success_rate"] >= 0.8, (summary, env_steps)
    assert num_options >= 3          # global + goal option + at least one link
    assert 0.0 <= summary["eval/chain_probability"] <= 1.0


@pytest.mark.slow
def test_mb_dscpp_learns_point_four_rooms(background, request):
    # budget: 48 iterations x 1,600 = 77k env steps (3 measured seeds reached 100 % after 56-64k;
    # experiments/results/train_point_four_rooms)
    summary, env_steps, num_options = _result(background, request)
    assert summary["eval/success_rate"] >= 0.8, (summary, env_steps)
    # the chain, not the global option, gets there: at least one link, and the global option ran
    # for less than half of the evaluation's steps (a point-mass link can reach across a room, so
    # the number of links alone says little)
    assert num_options >= 3 and summary["eval/global_option_share"] < 0.5, (summary, num_options)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["dsc"])
def test_baselines_learn_point_u_maze(algo, background, request):
    """A policy that learned nothing reaches the goal from none or one of the route starts; the
    chain must have grown beyond the goal option to cover them."""
    best, env_steps, num_options, train_success = _result(background, request)
    assert best >= DSC_LEARN_THRESHOLD, (best, env_steps, num_options, train_success)
    assert num_options >= 3, num_options

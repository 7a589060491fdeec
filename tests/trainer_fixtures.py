"""Small trainer configurations, tree comparisons and background learning jobs shared by the
trainer tests."""
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor

import jax
import numpy as np

from dscpp_jax import checkpoint as ck
from dscpp_jax.config import preset


# the fields `tiny` sets on the point U-maze's fast preset
TINY = dict(num_envs=4, steps_per_iter=20, total_env_steps=10_000, episode_length=100,
            warmup_episodes=2, max_options=4, max_pos_traj=8, max_neg=8, buffer_len=10,
            option_timeout=40, gestation=2, td3_hidden=32, td3_batch_size=32,
            td3_updates_per_step=0.1, replay_capacity=2000, model_capacity=2000,
            dyn_hidden=16, dyn_batch_size=32, dyn_updates_per_step=0.05, dyn_pretrain_steps=5,
            mpc_samples=32, mpc_horizon=3, eval_episodes=2, eval_every=0, checkpoint_every=0)


def tiny(algo="mf_dscpp", **kw):
    return preset("fast", "point_u_maze", algo, **{**TINY, **kw})


def assert_trees_equal(a, b):
    la, ta = jax.tree_util.tree_flatten(ck.to_storable(a))
    lb, tb = jax.tree_util.tree_flatten(ck.to_storable(b))
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def worker_output_to(path):
    """A worker's initializer: its stdout and stderr go to file `path` (JAX's and the ant's
    warnings)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    os.dup2(fd, 1)
    os.dup2(fd, 2)


def worker_on_spare_cores(path):
    """As `worker_output_to`, and the worker leaves one core to the test process (XLA's CPU
    runtime would take them all: on two cores the tests would wait for it)."""
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) > 1:
        for thread in os.listdir("/proc/self/task"):   # those started so far; later ones inherit
            os.sched_setaffinity(int(thread), cores[1:])
    worker_output_to(path)


def background_jobs(request, tmp_path_factory, jobs, workers=None, setup=worker_output_to):
    """The body of a module-scoped fixture: starts the jobs {test name: (function, arguments)}
    of the tests of the fixture's module that this session runs, before the module's first test,
    in `workers` worker processes (default: one per job; spawned, so each is a fresh JAX) that
    `setup(log path)` initialises; yields {test name: future}, then shuts the workers down."""
    selected = [n for n in jobs if any(getattr(item, "module", None) is request.module
                                       and item.name == n for item in request.session.items)]
    if not selected:
        yield {}
        return
    log = str(tmp_path_factory.mktemp("background") / "worker.log")
    pool = ProcessPoolExecutor(workers or len(selected),
                               mp_context=multiprocessing.get_context("spawn"),
                               initializer=setup, initargs=(log,))
    futures = {n: pool.submit(jobs[n][0], *jobs[n][1]) for n in selected}
    yield futures
    pool.shutdown(wait=True, cancel_futures=True)

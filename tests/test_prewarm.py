"""Building MuJoCo Warp's kernels while XLA compiles (`trainer.prewarm_physics`): the training
loops compile ahead of time (a single run `init` and its step, `trainer.compile_ahead`; a group
its step) and wait for the kernel build before anything runs the physics, without compiling
anything twice; `AntMazeEnv.build_warp_kernels` steps the model through MuJoCo
Warp outside JAX."""
import threading

import jax
import pytest

from dscpp_jax import envs, group_train
from dscpp_jax import seed_group as SG
from dscpp_jax import trainer as T
from dscpp_jax.envs.ant_maze import warp_available
from dscpp_jax.host_loop import train
from tests.trainer_fixtures import tiny


def _started_thread(ran, order):
    order.append("prewarm")
    t = threading.Thread(target=lambda: ran.append(1))
    t.start()
    return t


def _compiles(fn):
    """(fn's result, the names of the functions XLA compiled meanwhile)."""
    events = []
    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append(kw.get("fun_name"))
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        out = fn()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return out, events


def test_loops_compile_ahead_and_wait_for_the_kernel_build(tmp_path, monkeypatch):
    # on a CPU there is nothing to build (prewarm_physics returns None); stand in a thread so
    # that the single-run and the group loop take the path they take on a GPU. The runs with it
    # use a config of their own, so their step compiles afresh: the ahead-of-time compile must be
    # the only compile of the step, as the first call is without it.
    assert T.prewarm_physics(tiny("td3_her")) is None
    cfgs = [tiny("td3_her", total_env_steps=160, td3_hidden=h) for h in (24, 40)]
    (state, _), plain = _compiles(lambda: train(cfgs[0], str(tmp_path / "a"), progress=False))
    (_, _, _), plain_group = _compiles(lambda: group_train.train_group(
        cfgs[0], [0, 1], str(tmp_path / "ga"), progress=False))
    ran, order = [], []
    monkeypatch.setattr(T, "prewarm_physics", lambda cfg: _started_thread(ran, order))
    # `init` steps the env through MuJoCo Warp, and Warp launches from two threads at once crash
    # (seen on a GPU with warm caches): a single run compiles `init` and the step ahead while the
    # thread builds, and runs `init` after it; a group starts the thread once its states exist
    for mod, name in ((T, "init"), (SG, "init_group")):
        real = getattr(mod, name)
        monkeypatch.setattr(mod, name, lambda *a, _real=real, _n=name, **k: (
            order.append(_n), _real(*a, **k))[1])
    (state, _), ahead = _compiles(lambda: train(cfgs[1], str(tmp_path / "b"), progress=False))
    assert int(state.counters.iteration) == 2 and ran == [1]
    (states, _, _), ahead_group = _compiles(lambda: group_train.train_group(
        cfgs[1], [0, 1], str(tmp_path / "gb"), progress=False))
    assert ran == [1, 1] and [int(i) for i in states.counters.iteration] == [2, 2]
    # (init_group calls init once per seed)
    assert order[:2] == ["prewarm", "init"] and order[2:] == ["init_group", "init", "init", "prewarm"], order
    # the step programs: train_step_impl (single run), step (the group's shard_map body)
    def steps(names, step):
        return sum(n == f"jit({step})" for n in names)
    assert steps(plain, "train_step_impl") == steps(ahead, "train_step_impl") == 1
    assert steps(plain, "init_impl") == steps(ahead, "init_impl") == 1
    assert steps(plain_group, "step") == steps(ahead_group, "step") == 1


def test_build_warp_kernels_steps_the_model_outside_jax():
    assert envs.make("u_maze", physics="jax").build_warp_kernels("cpu") is False
    if not warp_available():
        pytest.skip("warp-lang is not installed")
    env = envs.make("u_maze", physics="warp", warp_worlds=2)
    assert env.build_warp_kernels("cpu") is True
    if jax.default_backend() != "gpu":
        import warp as wp
        assert env.build_warp_kernels() is wp.is_cuda_available()


def test_warp_build_workers_come_from_the_environment(monkeypatch):
    monkeypatch.delenv(T.WARP_BUILD_WORKERS_ENV, raising=False)
    assert T.warp_build_workers() == 0
    monkeypatch.setenv(T.WARP_BUILD_WORKERS_ENV, " 4 ")
    assert T.warp_build_workers() == 4
    for bad in ("four", "-1", "2.5"):
        monkeypatch.setenv(T.WARP_BUILD_WORKERS_ENV, bad)
        with pytest.raises(ValueError, match="whole number of threads"):
            T.warp_build_workers()
        with pytest.raises(ValueError, match="whole number of threads"):
            T.prewarm_physics(tiny())   # read before anything is built, on any platform

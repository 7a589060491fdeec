"""`envs.warp_kernels`: the dry run finds every Warp module MuJoCo Warp's step loads, launches
nothing on its own thread and only there, and leaves Warp as it found it; `load_modules` loads
them so that the real step has nothing left to build. On Warp's CPU device."""
import threading

import numpy as np
import pytest

from dscpp_jax.envs.ant_maze import warp_available

pytestmark = pytest.mark.skipif(not warp_available(), reason="warp-lang is not installed")


def _model_and_data():
    import warp as wp
    from mujoco.mjx.third_party import mujoco_warp as mjwarp

    from dscpp_jax import envs
    env = envs.make("u_maze", physics="warp", warp_worlds=1)
    with wp.ScopedDevice("cpu"):
        m, d = env.warp_one_world()
    return mjwarp, m, d


def _loads_during(fn):
    """The modules whose `load` `fn` calls, and those of them it had to build or load anew."""
    import warp as wp
    orig = wp.Module.load
    asked, new = [], []

    def load(self, device, block_dim=None, *a, **k):
        before = len(self.execs)
        out = orig(self, device, block_dim, *a, **k)
        asked.append(self)
        if len(self.execs) != before:
            new.append(self)
        return out

    wp.Module.load = load
    try:
        fn()
    finally:
        wp.Module.load = orig
    return asked, new


def test_dry_run_finds_the_step_modules_and_load_modules_leaves_nothing_to_build():
    import warp as wp

    from dscpp_jax.envs.warp_kernels import load_modules, modules_launched
    mjwarp, m, d = _model_and_data()
    with wp.ScopedDevice("cpu"):
        qpos, time0 = d.qpos.numpy().copy(), d.time.numpy().copy()
        found = modules_launched(lambda: mjwarp.step(m, d))
        # nothing ran: the state is where it was
        np.testing.assert_array_equal(d.qpos.numpy(), qpos)
        np.testing.assert_array_equal(d.time.numpy(), time0)
        assert len(found) >= 10, found   # the ant's step: about 30 modules
        mods = {id(x[0]) for x in found}

        # without the parallel load, the real step builds (or reads from the cache) every module
        for mod, _, _ in found:
            mod.unload()
        asked, new = _loads_during(lambda: mjwarp.step(m, d))
        assert {id(x) for x in asked} <= mods, "the dry run missed a module the step loads"
        assert len({id(x) for x in new}) == len(mods)

        # with it, the real step has nothing left to load, and it did step
        for mod, _, _ in found:
            mod.unload()
        assert load_modules(found, workers=2) == len(found)
        t1 = float(d.time.numpy()[0])
        asked, new = _loads_during(lambda: mjwarp.step(m, d))
        assert asked and not new, [x.name for x in new]
        assert float(d.time.numpy()[0]) > t1


def test_dry_run_is_confined_to_its_thread_and_restores_warp():
    import warp as wp

    from dscpp_jax.envs import warp_kernels as W
    from tests.warp_kernel_fixture import add_one
    orig = (wp.Module.load, wp.capture_while, wp.capture_if)
    mine = wp.zeros(4, dtype=float, device="cpu")
    other = wp.zeros(4, dtype=float, device="cpu")

    def fn():
        wp.launch(add_one, dim=4, inputs=[mine], device="cpu")
        t = threading.Thread(target=lambda: wp.launch(add_one, dim=4, inputs=[other], device="cpu"))
        t.start()
        t.join()
        cond = wp.ones(1, dtype=wp.int32, device="cpu")   # would loop for ever if it were read
        wp.capture_while(cond, while_body=lambda: wp.launch(add_one, dim=4, inputs=[mine],
                                                               device="cpu"))

    found = W.modules_launched(fn)
    assert [x[0] for x in found] == [add_one.module]
    np.testing.assert_array_equal(mine.numpy(), 0.0)    # this thread launched nothing
    np.testing.assert_array_equal(other.numpy(), 1.0)   # the other thread's launch ran
    assert (wp.Module.load, wp.capture_while, wp.capture_if) == orig

    def boom():
        raise RuntimeError("boom")
    with pytest.raises(RuntimeError, match="boom"):
        W.modules_launched(boom)
    assert (wp.Module.load, wp.capture_while, wp.capture_if) == orig
    wp.launch(add_one, dim=4, inputs=[mine], device="cpu")
    np.testing.assert_array_equal(mine.numpy(), 1.0)


def test_bench_warp_build_rejects_bad_settings():
    from tests.experiment_scripts import load
    B = load("bench_warp_build")
    for argv in (["--workers", "-1"], ["--repeat", "0"]):
        with pytest.raises(SystemExit):
            B.main(argv)


def test_build_covers_the_jax_step_of_many_worlds():
    """`build_warp_kernels` steps one world; the jitted JAX step of several worlds (what training
    runs) then finds every MuJoCo Warp physics module loaded (MJX's own JAX glue, whose kernels
    are generic and typed at the call, aside)."""
    import jax
    import jax.numpy as jnp

    from dscpp_jax import envs
    from warp._src.context import user_modules
    env = envs.make("u_maze", physics="warp", warp_worlds=3)
    for mod in list(user_modules.values()):   # what earlier tests loaded in this process
        mod.unload()
    assert env.build_warp_kernels("cpu") is True

    @jax.jit
    def roll(keys, acts):
        s = jax.vmap(env.reset)(keys)
        return jax.lax.scan(lambda s, a: (jax.vmap(env.step)(s, a), None), s, acts)[0].obs

    keys = jax.random.split(jax.random.key(0), 3)
    acts = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (2, 3, 8)), jnp.float32)
    asked, new = _loads_during(lambda: jax.block_until_ready(roll(keys, acts)))
    physics = [x.name for x in new if not x.name.startswith("mujoco.mjx.warp.")]
    assert asked and not physics, physics


def test_warp_one_world_carries_the_env_solver_options_and_sizes():
    import dataclasses

    import warp as wp

    from dscpp_jax import envs
    env = envs.make("u_maze", physics="warp", warp_worlds=1)
    with wp.ScopedDevice("cpu"):
        m, d = env.warp_one_world()
    impl = env.mjx_model.opt._impl
    checked = 0
    for f in dataclasses.fields(m.opt):
        v = getattr(impl, f.name, None)
        if isinstance(v, (bool, int, float)) and type(v) is type(getattr(m.opt, f.name)):
            assert getattr(m.opt, f.name) == v, f.name
            checked += 1
    assert checked > 0
    assert m.opt.warn_overflow == impl.warn_overflow
    assert d.naconmax == env.config.warp_contacts_per_world
    assert d.njmax == env.config.warp_constraints_per_world


def test_dry_run_answers_get_suggested_block_size_on_cuda_without_loading(monkeypatch):
    """On a CUDA device Warp's occupancy query loads the kernel's module (MuJoCo Warp's collision
    asks it before a launch); in a dry run it notes the module and answers a placeholder. Tested
    on the CPU device taken for a CUDA one."""
    import warp as wp

    from dscpp_jax.envs import warp_kernels
    from tests.warp_kernel_fixture import add_one
    monkeypatch.setattr(warp_kernels, "_is_cuda", lambda device: True)
    answers = []
    found = warp_kernels.modules_launched(
        lambda: answers.append(wp.get_suggested_block_size(add_one, "cpu")))
    assert answers == [warp_kernels.DRY_BLOCK_SIZE]
    assert [m for m, _, _ in found] == [add_one.module]
    # restored: outside the dry run the real query answers (on a CPU device: (1, 1))
    monkeypatch.undo()
    assert wp.get_suggested_block_size(add_one, "cpu") == (1, 1)


def test_build_falls_back_to_the_plain_step_when_the_dry_run_fails(monkeypatch):
    from dscpp_jax import envs
    from dscpp_jax.envs import warp_kernels

    def broken(fn):
        raise RuntimeError("dry run broke")

    monkeypatch.setattr(warp_kernels, "modules_launched", broken)
    env = envs.make("u_maze", physics="warp", warp_worlds=1)
    with pytest.warns(UserWarning, match="dry run of the step failed"):
        assert env.build_warp_kernels("cpu", workers=2)

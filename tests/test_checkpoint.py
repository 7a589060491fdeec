"""Whole-state checkpoints: round trip, and resume equivalence (N straight == N/2 + save + restore
+ N/2 on the same device with the same seed)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import checkpoint as ck
from dscpp_jax import trainer as T
from tests.trainer_fixtures import assert_trees_equal, tiny


def test_roundtrip_with_typed_keys(tmp_path):
    tree = {"a": jnp.arange(5.0), "k": jax.random.key(3), "raw": jax.random.PRNGKey(1),
            "flag": jnp.zeros((), bool), "none": None}
    ck.save_state(str(tmp_path), 7, tree)
    assert ck.latest_step(str(tmp_path)) == 7
    back = ck.restore_state(str(tmp_path), tree)
    assert jax.dtypes.issubdtype(back["k"].dtype, jax.dtypes.prng_key)
    np.testing.assert_array_equal(jax.random.key_data(back["k"]), jax.random.key_data(tree["k"]))
    np.testing.assert_array_equal(back["a"], tree["a"])
    with pytest.raises(FileNotFoundError):
        ck.restore_state(str(tmp_path / "missing"), tree)


def test_background_save_prunes_only_after_its_read_back(tmp_path, monkeypatch):
    """`save(wait=False)` returns while the write's end, read-back and pruning are still to come
    (held here on an event); the older checkpoint stays until then, and the result is a plain
    save's."""
    import threading
    run = str(tmp_path)
    tree = {"a": jnp.arange(6.0), "k": jax.random.key(5)}
    c = ck.Checkpointer(run, keep=1)
    c.save(1, tree)
    gate, finishing = threading.Event(), []
    plain_finish = ck.Checkpointer._finish

    def held_finish(self, step, like):
        finishing.append(step)
        assert gate.wait(60)
        plain_finish(self, step, like)
    monkeypatch.setattr(ck.Checkpointer, "_finish", held_finish)
    tree2 = {"a": jnp.arange(6.0) + 10.0, "k": jax.random.key(6)}
    c.save(2, tree2, wait=False)                 # returns with the finish held
    assert c._worker is not None and c._worker.is_alive()
    assert 1 in c._steps()                       # not pruned before the new one reads back
    gate.set()
    c.wait()
    assert finishing == [2] and c.all_steps() == [2]
    c.close()
    back = ck.restore_state(run, tree)
    np.testing.assert_array_equal(back["a"], tree2["a"])
    np.testing.assert_array_equal(jax.random.key_data(back["k"]), jax.random.key_data(tree2["k"]))


def test_background_save_error_surfaces_at_the_next_call(tmp_path, monkeypatch):
    run = str(tmp_path)
    tree = {"a": jnp.arange(4.0)}
    c = ck.Checkpointer(run, keep=1)
    c.save(1, tree)
    monkeypatch.setattr(ck.Checkpointer, "_read_back",
                        lambda self, step, like: (_ for _ in ()).throw(ValueError("Invalid JSON")))
    c.save(2, tree, wait=False)                  # no error yet: it is raised where one waits
    with pytest.raises(ck.CheckpointError, match="iteration 2 did not read back"):
        c.save(3, tree)
    assert c.all_steps() == [1]                  # the older one stays; 2 was set aside
    c.save(3, tree, wait=False)
    with pytest.raises(ck.CheckpointError, match="iteration 3 did not read back"):
        c.close()
    monkeypatch.undo()
    assert ck.all_steps(run) == [1]
    np.testing.assert_array_equal(ck.restore_state(run, tree)["a"], tree["a"])


def test_background_write_error_surfaces_at_the_next_call(tmp_path, monkeypatch):
    """In the background the write itself runs on the worker (the loop only copies the state to
    host memory), so a write that fails is reported where one waits, and the older checkpoint
    stays."""
    run = str(tmp_path)
    tree = {"a": jnp.arange(4.0)}
    c = ck.Checkpointer(run, keep=1)
    c.save(1, tree)
    plain_save = c.manager.save
    calls = []

    def full_disk(step, *a, **k):
        calls.append(step)
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(c.manager, "save", full_disk)
    c.save(2, tree, wait=False)                  # returns: the write is the worker's
    with pytest.raises(ck.CheckpointError, match="could not save the checkpoint of iteration 2"):
        c.wait()
    assert calls == [2] and c.all_steps() == [1]
    monkeypatch.setattr(c.manager, "save", plain_save)
    c.save(3, {"a": jnp.arange(4.0) + 1.0}, wait=False)
    c.close()
    assert ck.all_steps(run) == [3]
    np.testing.assert_array_equal(ck.restore_state(run, tree)["a"], np.arange(4.0) + 1.0)


def test_orbax_false_wait_warning_is_dropped_and_others_kept(tmp_path, caplog):
    from absl import logging as absl_logging
    ck.Checkpointer(str(tmp_path))         # installs the filter (once, however often)
    ck.quiet_orbax()
    caplog.set_level("WARNING")
    absl_logging.warning("Waiting for previous save to complete took %f seconds. If this"
                         " number is high, consider checkpointing less frequently.", 6.5)
    absl_logging.warning("something else from orbax")
    assert [r.getMessage() for r in caplog.records] == ["something else from orbax"]


@pytest.mark.parametrize("algo", ["mb_dscpp", "mf_dscpp"])
def test_resume_equivalence(tmp_path, algo):
    cfg = tiny(algo)
    s0 = T.init(jax.random.PRNGKey(3), cfg)
    straight = s0
    for _ in range(4):
        straight, _ = T.train_step(straight)
    half = s0
    for _ in range(2):
        half, _ = T.train_step(half)
    ck.save_state(str(tmp_path), int(half.counters.iteration), half)
    fresh = T.init(jax.random.PRNGKey(99), cfg)          # different contents, same structure
    resumed = ck.restore_state(str(tmp_path), fresh)
    assert_trees_equal(resumed, half)
    n_compiled = T.train_step._cache_size()
    for _ in range(2):
        resumed, _ = T.train_step(resumed)
    assert T.train_step._cache_size() == n_compiled   # a restored state does not recompile
    assert int(resumed.counters.iteration) == 4
    assert_trees_equal(resumed, straight)


def test_bench_checkpoint_smoke(tmp_path):
    """experiments/bench_checkpoint.py on a point maze: one run and a 2-seed group, both ways."""
    import json

    from tests.experiment_scripts import load
    bench = load("bench_checkpoint")
    out = str(tmp_path / "b.json")
    assert bench.main(["--env", "point_u_maze", "--algo", "td3_her", "--seeds-list", "1,2",
                       "--repeat", "1", "--filled", "--dir", str(tmp_path / "ck"),
                       "--out", out]) == 0
    res = json.load(open(out))["results"]
    assert [r["seeds"] for r in res] == [1, 2]
    for r in res:
        assert r["state_mb"] > 0 and r["plain_blocked_s"] > 0
        assert 0 < r["background_blocked_s"] <= r["background_finished_s"]
    assert all(r["filled"] for r in res)
    with pytest.raises(SystemExit):
        bench.main(["--seeds-list", "0"])
    tree = {"f": jnp.zeros((3, 4), jnp.bfloat16), "i": jnp.arange(5), "k": jax.random.key(1),
            "e": jnp.zeros((0,), jnp.float32)}
    got = bench.filled(tree)
    assert got["f"].dtype == jnp.bfloat16 and got["f"].shape == (3, 4)
    assert np.all(np.asarray(got["f"], np.float32) != 0)
    np.testing.assert_array_equal(got["i"], tree["i"])
    np.testing.assert_array_equal(jax.random.key_data(got["k"]), jax.random.key_data(tree["k"]))
    assert got["e"].shape == (0,)


def test_bench_group_save_smoke(tmp_path):
    """experiments/bench_group_save.py on a small synthetic group state: every round of both
    ways timed, compile counts recorded, the JSON written."""
    import json as _json

    from tests.experiment_scripts import load
    bench = load("bench_group_save")
    out = str(tmp_path / "g.json")
    res = bench.main(["--seeds", "2", "--small", "5", "--buffer-rows", "100000", "--rounds", "2",
                      "--out", out])
    assert res == _json.load(open(out))
    assert res["seeds"] == 2 and res["arrays"] == 7 and res["gbytes"] > 0.02
    assert res["gbytes"] == round((2 * 100000 * 20 + 2 * 30000 * 32
                                   + sum(2 * ((i % 37) + 1) * ((i % 11) + 1) for i in range(5)))
                                  * 4 / 1e9, 3)
    for way in ("orbax_async", "device_get"):
        assert [r["step"] for r in res[way]] == [0, 1]
        assert all(r["hold_s"] >= 0 and isinstance(r["compiles"], int) for r in res[way])
    assert all(r["total_s"] >= r["hold_s"] for r in res["orbax_async"])

"""Seed groups: N seeds in one program equal N separate runs; sharded over a 4-device mesh and over
two processes they equal the unsharded group; kill -9 and resume equals the uninterrupted group;
seed directories work with eval and plot; --seeds errors are clear.

All on the flat td3_her algorithm (the smallest program to compile) and the point-mass U-maze.
The group program is compiled once in this process (module fixtures) and stored in a compilation
cache that the killed subprocess loads.

Tolerances: a group vmaps the training step, and XLA computes vmapped matrix products as batched
products whose sums may run in another order, so floats of a seed in a group differ from its
separate run by rounding (about 1e-7 relative after an iteration); counters and every discrete
quantity are compared exactly.
"""
import argparse
import importlib
import json
import os
import socket
import subprocess
import sys
import types
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

import dscpp_jax
from dscpp_jax import diagnose, group_train, host_loop
from dscpp_jax import checkpoint as ck
from dscpp_jax import seed_group as SG
from dscpp_jax import trainer as T
from dscpp_jax.cli import deterministic_choice, main, parse_overrides
from dscpp_jax.config import preset
from dscpp_jax.envs import ant_maze
from dscpp_jax.envs.ant_maze import warp_available
from dscpp_jax.evaluate import evaluate
from dscpp_jax.run_dir import load_run
from dscpp_jax.run_logging import read_metrics, read_startup
from tests.trainer_fixtures import assert_trees_equal

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = ["num_envs=4", "steps_per_iter=20", "episode_length=100", "warmup_episodes=2",
        "td3_hidden=32", "td3_batch_size=32", "td3_updates_per_step=0.1", "replay_capacity=2000",
        "eval_episodes=2"]
TOTAL = 480   # 6 iterations of 4 envs x 20 steps
TRAIN = ["train", "--env", "point_u_maze", "--algo", "td3_her", "--total-steps", str(TOTAL),
         "--eval-every", "2", "--checkpoint-every", "1", "--no-progress"]
for _s in TINY:
    TRAIN += ["--set", _s]
RTOL = 1e-4


def group_config():
    """The config that TRAIN gives (for the API)."""
    return preset("fast", "point_u_maze", "td3_her", **parse_overrides(TINY))
SKIP = ("wall_clock", "time/")


def _env(**extra):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
    env.update(extra)
    return env


def _compare_metrics(a_dir, b_dir, rtol=RTOL, rows=None):
    a, b = read_metrics(a_dir), read_metrics(b_dir)
    assert a["iteration"][:rows] == b["iteration"][:rows] and len(a["iteration"]) >= 3
    for col in a:
        if col.startswith(SKIP) or col not in b:
            continue
        exact = col in ("iteration", "env_steps", "episodes") or col.startswith("counters/")
        np.testing.assert_allclose(a[col][:rows], b[col][:rows], rtol=0 if exact else rtol,
                                   atol=0 if exact else 1e-6, equal_nan=True, err_msg=col)


def _compare_states(a, b, rtol=RTOL):
    np.testing.assert_array_equal(np.asarray(a.counters.env_steps), np.asarray(b.counters.env_steps))
    np.testing.assert_array_equal(np.asarray(a.counters.episodes), np.asarray(b.counters.episodes))
    for x, y in [(a.td3.critic_params, b.td3.critic_params), (a.td3.actor_params, b.td3.actor_params),
                 (a.replay.data, b.replay.data), (a.env_state.obs, b.env_state.obs)]:
        for u, v in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)):
            np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=rtol, atol=1e-5)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A compilation cache for this process's programs (set before its first compilation), so the
    killed subprocess below loads the group program instead of compiling it again."""
    d = str(tmp_path_factory.mktemp("xla_cache"))
    jax.config.update("jax_compilation_cache_dir", d)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return d


@pytest.fixture(scope="module")
def background(tmp_path_factory):
    """The 4-device and the two-process runs, started at once in subprocesses so that they compile
    while this process does (2 CPU cores); the tests below wait for their results."""
    base = tmp_path_factory.mktemp("background")
    pool = ThreadPoolExecutor(2)
    runs = {"four": pool.submit(_run_four_devices, str(base / "four.json")),
            "two": pool.submit(_run_two_processes, str(base / "two"), str(base / "cache"))}
    yield runs
    pool.shutdown(wait=True)


@pytest.fixture(scope="module")
def ref(cache, background, tmp_path_factory):
    """The uninterrupted group of seeds 0 and 1 through the command line."""
    group = str(tmp_path_factory.mktemp("groups") / "ref")
    assert main(TRAIN + ["--seeds", "0-1", "--run-dir", group]) == 0
    return group


def test_seed_lists_and_cli_errors(capsys, tmp_path):
    assert SG.parse_seeds("0-3,7,9") == (0, 1, 2, 3, 7, 9)
    assert SG.parse_seeds(" 5 ") == (5,) and SG.format_seeds((0, 1, 2, 3, 7, 9)) == "0-3_7_9"
    for bad, msg in (("3-1", "runs backwards; write it as 1-3"), ("a", "cannot read 'a'"),
                     ("0-2,2", "more than once"), ("", "cannot read")):
        with pytest.raises(ValueError, match=msg):
            SG.parse_seeds(bad)
        assert main(["train", "--seeds", bad, "--run-dir", str(tmp_path / "x")]) == 2
        assert msg.split(";")[0] in capsys.readouterr().err
    assert main(["train", "--seed", "1", "--seeds", "0-1", "--run-dir", str(tmp_path / "y")]) == 2
    assert "either --seed N (one run) or --seeds LIST" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"3 seeds do not divide evenly over 2 devices; .*\(2, 4, 6"):
        SG.check_group_size(3, types.SimpleNamespace(size=2))
    SG.check_group_size(4, types.SimpleNamespace(size=2))


def test_leaf_rule_shards_group_sized_leaves_and_replicates_the_rest():
    tree = {"per_seed": np.zeros((3, 5)), "shared": np.zeros((7, 3)), "scalar": np.zeros(())}
    assert SG.group_specs(tree, 3) == {"per_seed": P("seeds"), "shared": P(), "scalar": P()}


def test_group_equals_separate_runs(ref, tmp_path):
    cfg = group_config()
    # the initial states are exactly those of separate runs
    g = SG.init_group([3, 5], cfg)
    # (a group's config records its size, which sizes what its seeds share; nothing else differs)
    assert SG.seed_state(g, 1).config.run.group_size == 2
    assert_trees_equal(SG.seed_state(g, 1), T.init(jax.random.PRNGKey(5), cfg.override(group_size=2)))
    for s in (0, 1):
        single = str(tmp_path / f"single{s}")
        assert main(TRAIN + ["--seed", str(s), "--run-dir", single]) == 0
        _compare_metrics(os.path.join(ref, f"s{s}"), single)
        _, a = load_run(os.path.join(ref, f"s{s}"))          # the seed out of the group checkpoint
        _, b = load_run(single)
        _compare_states(a, b)
        ev_a = json.load(open(os.path.join(ref, f"s{s}", "eval.json")))
        assert ev_a["seed"] == s and ev_a["iteration"] == 6
    gj = json.load(open(os.path.join(ref, "group.json")))
    assert gj["seeds"] == [0, 1] and gj["mesh"] == {"seeds": 1} and "jax" in gj["versions"]
    st = read_startup(ref)   # the group's start, once
    assert len(st) == 1 and st[0]["seeds"] == [0, 1] and "first iteration" in st[0]["phases_s"]
    assert json.load(open(os.path.join(ref, "s1", "config.json")))["config"]["run"]["seed"] == 1
    assert not os.path.exists(os.path.join(ref, "s0", "checkpoints"))   # one group checkpoint


def test_group_evaluation_with_exploration_equals_each_seed():
    g = SG.init_group([3, 5], group_config())
    summ, res = SG.evaluate_group(g, num_episodes=2, explore=True)
    for i in (0, 1):
        one, r = evaluate(SG.seed_state(g, i), num_episodes=2, explore=True)
        np.testing.assert_allclose(np.asarray(res.xy[i]), np.asarray(r.xy), rtol=1e-4, atol=1e-5)
        assert summ[i]["eval/success_rate"] == one["eval/success_rate"]
    assert not np.allclose(np.asarray(res.xy), np.asarray(SG.evaluate_group(g, num_episodes=2)[1].xy))


def test_kill_and_resume_equals_uninterrupted_and_seed_dirs_work(ref, cache, tmp_path, capsys):
    group = str(tmp_path / "killed")
    code = (
        "import os, signal, sys\n"
        "from dscpp_jax import seed_group as SG\n"
        "from dscpp_jax.cli import main\n"
        "real, calls = SG.train_step_group, [0]\n"
        "def step(*a, **k):\n"
        "    calls[0] += 1\n"
        "    if calls[0] == 4:\n"
        "        os.kill(os.getpid(), signal.SIGKILL)   # in the middle of iteration 4\n"
        "    return real(*a, **k)\n"
        "SG.train_step_group = step\n"
        f"sys.exit(main({TRAIN + ['--seeds', '0-1', '--run-dir', group, '--compile-cache', cache]!r}))\n")
    r = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True,
                       cwd=ROOT, timeout=600)
    assert r.returncode == -9, r.stderr[-3000:]
    assert read_metrics(os.path.join(group, "s0"))["iteration"] == [1.0, 2.0, 3.0]
    assert main(["train", "--resume", group, "--no-progress"]) == 0
    for s in (0, 1):
        _compare_metrics(os.path.join(ref, f"s{s}"), os.path.join(group, f"s{s}"), rtol=0)
        assert_trees_equal(load_run(os.path.join(group, f"s{s}"))[1],
                           load_run(os.path.join(ref, f"s{s}"))[1])
    capsys.readouterr()
    # each seed directory works with eval and plot (the state comes from the group checkpoint)
    s1 = os.path.join(group, "s1")
    assert main(["eval", "--run", s1, "--episodes", "2", "--no-plot"]) == 0
    assert json.load(open(os.path.join(s1, "eval.json")))["iteration"] == 6
    out = str(tmp_path / "plots")
    assert main(["plot", os.path.join(group, "s0"), s1, "--out", out]) == 0
    for f in ("curves.png", "s0_trajectory.png", "s1_trajectory.png"):
        assert os.path.getsize(os.path.join(out, f)) > 1000
    # the group directory: every seed in one call, each as its own seed directory's evaluation
    s1_alone = json.load(open(os.path.join(s1, "eval.json")))
    capsys.readouterr()
    assert main(["eval", "--run", group, "--episodes", "2", "--no-plot"]) == 0
    out = capsys.readouterr().out
    assert "seed 0: success" in out and "seed 1: success" in out and "2 seeds: success" in out
    together = json.load(open(os.path.join(s1, "eval.json")))
    assert together["seed"] == 1 and together["iteration"] == 6
    assert together["eval/success_rate"] == s1_alone["eval/success_rate"]
    assert together["eval/steps_to_goal"] == pytest.approx(s1_alone["eval/steps_to_goal"],
                                                           rel=1e-4, nan_ok=True)
    assert main(["eval", "--run", group, "--episodes", "2", "--explore", "--step", "5",
                 "--no-plot"]) == 0
    ex = json.load(open(os.path.join(group, "s0", "eval_explore_step5.json")))
    assert ex["explore"] is True and ex["iteration"] == 5
    assert main(["eval", "--run", group, "--step", "1"]) == 2
    assert "no checkpoint of step 1" in capsys.readouterr().err


def test_a_diverged_seed_stops_the_group_and_is_named(ref, tmp_path, monkeypatch, capsys):
    real = SG.train_step_group

    def step(states, *a, **k):
        states, m = real(states, *a, **k)
        if int(np.asarray(SG.to_host(states.counters.iteration))[0]) == 2:   # seed 1 diverges
            m = dict(m, **{"finite/td3": m["finite/td3"].at[1].set(0.0)})
        return states, m
    monkeypatch.setattr(SG, "train_step_group", step)
    group = str(tmp_path / "nan")
    assert main(TRAIN + ["--seeds", "0-1", "--run-dir", group]) == 3
    err = capsys.readouterr().err
    assert "diverged at iteration 2 (seed 1: the TD3 actor/critic parameters)" in err
    assert "whole group stopped" in err
    assert ck.latest_step(group) == 1           # the last finite group state


def test_readme_seed_group_example_runs(ref, capsys):
    """The README's seed-group lines, on the tiny config compiled above."""
    text = open(os.path.join(ROOT, "README.md")).read()
    block = text.split("# several seeds in one jitted program", 1)[1].split("```", 1)[0]
    block = block.split("\n", 1)[1]      # the lines after that comment, to the block's end
    exec(compile(block, "README seed-group example", "exec"), {"jax": jax, "dscpp_jax": dscpp_jax,
                                              "cfg": group_config()})
    rates = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(rates) == 2 and all(0.0 <= r <= 1.0 for r in rates)


def _experiment(name: str):
    """A script of experiments/ imported as a module."""
    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)


def test_bench_seeds_smoke(ref, tmp_path):
    """experiments/bench_seeds.py on the tiny config (its program is in the compilation cache); a
    group size that fails is recorded, not fatal."""
    bench_seeds = _experiment("bench_seeds")
    out = str(tmp_path / "bench.json")
    sets = [a for s in TINY for a in ("--set", s)]
    assert bench_seeds.main(["--env", "point_u_maze", "--algos", "td3_her", "--seeds-list", "2,0",
                             "--devices-list", "1", "--per-device", "--iters", "2",
                             "--out", out] + sets) == 0
    res = json.load(open(out))["results"]
    assert res[0]["N"] == 2 and res[0]["env_steps_per_s"] > 0 and res[0]["compile_s"] > 0
    assert "at least one seed" in res[1]["error"]
    assert "| td3_her | 2 | 1 |" in open(out[:-5] + ".md").read()
    with pytest.raises(SystemExit):      # more devices than this host has
        bench_seeds.main(["--devices-list", "1,3", "--out", out])


def test_bench_seeds_deterministic_default_is_train_s(monkeypatch):
    """The benchmark sets the switch once for all its algorithms, as `train` would: off where the
    ant physics is MuJoCo Warp, on otherwise, unless asked."""
    bench_seeds = _experiment("bench_seeds")
    monkeypatch.setattr(ant_maze, "warp_available", lambda: True)

    def det(*argv):
        p = argparse.ArgumentParser()
        p.add_argument("--env", default="u_maze")
        p.add_argument("--algos", default="mf_dscpp,mb_dscpp")
        p.add_argument("--set", action="append", default=[])
        p.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None)
        return deterministic_choice(bench_seeds.as_train(p.parse_args(list(argv))))

    assert not det()                                    # on Warp: off, model-based or not
    assert not det("--algos", "mf_dscpp")
    assert det("--deterministic")
    assert det("--set", "physics=jax")                  # MJX physics: on
    assert det("--env", "point_u_maze", "--algos", "mf_dscpp")   # no Warp: on


def test_profile_seed_group_smoke(ref, tmp_path):
    """experiments/profile_seed_group.py on the tiny config: every asked part and variant timed."""
    profile_seed_group = _experiment("profile_seed_group")
    out = str(tmp_path / "profile.json")
    sets = [a for s in TINY for a in ("--set", s)]
    assert profile_seed_group.main(["--env", "point_u_maze", "--algo", "td3_her", "--seeds-list",
                                    "2", "--parts", "td3,step", "--td3-variants", "fixed_batch",
                                    "--reps", "1", "--trace", "--hlo-dir", str(tmp_path / "hlo"),
                                    "--out", out] + sets) == 0
    row = json.load(open(out))["rows"][0]
    assert row["N"] == 2 and row["td3_s"] > 0 and row["td3_fixed_batch_s"] > 0
    tr = row["trace"]["td3"]    # the kernels of one traced call, summed by name
    assert tr["wall_s"] > 0 and tr["lines"]
    assert all(ln["events"] >= len(ln["top"]) > 0 for ln in tr["lines"].values())
    ops = [row["op"] for ln in tr["lines"].values() for row in ln["top"] if "op" in row]
    assert ops and all(isinstance(op, str) and op for op in ops)   # kernels traced to JAX ops
    assert "ENTRY" in (tmp_path / "hlo" / "td3_N2.hlo.txt").read_text()
    assert row["step_s"] > 0 and row["env_steps_per_s"] > 0 and "physics_s" not in row
    with pytest.raises(SystemExit):
        profile_seed_group.main(["--td3-variants", "unknown"] + sets)


FOUR_DEVICES = """
import json, sys
import jax, numpy as np
from dscpp_jax import seed_group as SG
from tests.test_seed_group import group_config
assert jax.device_count() == 4
states = SG.init_group([0, 1, 2, 3], group_config())
devs = sorted({d.id for d in states.counters.iteration.sharding.device_set})
out = {"devices": devs, "metrics": []}
fn, placed, active = SG.group_step_program(states)
out["shardy"] = "sdy." in fn.lower(placed, active).as_text()
for _ in range(3):
    states, m = SG.train_step_group(states)
    out["metrics"].append({k: np.asarray(v).tolist() for k, v in SG.to_host(m).items()})
summ, _ = SG.evaluate_group(states, num_episodes=2)
out["eval"] = [s["eval/success_rate"] for s in summ]
json.dump(out, open(sys.argv[1], "w"))
"""
def _run_four_devices(path):
    r = subprocess.run([sys.executable, "-c", FOUR_DEVICES, path], cwd=ROOT, timeout=900,
                       env=_env(XLA_FLAGS=" ".join(filter(None, (
                           os.environ.get("XLA_FLAGS"), "--xla_force_host_platform_device_count=4")))),
                       capture_output=True, text=True)
    return r.returncode, r.stderr[-3000:], path


def test_four_device_mesh_equals_the_unsharded_group(ref, background):
    """Seeds 0-3 on a 4-device CPU mesh (one seed per device) against the unsharded group."""
    rc, err, path = background["four"].result(timeout=900)
    assert rc == 0, err
    out = json.load(open(path))
    assert out["devices"] == [0, 1, 2, 3]          # one seed per device
    # several devices: lowered for GSPMD (Shardy's conversion crashed XLA's GPU compiler)
    assert out["shardy"] is False
    for s in (0, 1):
        m = read_metrics(os.path.join(ref, f"s{s}"))
        for it, row in enumerate(out["metrics"]):
            for k, v in row.items():
                if k in m:
                    np.testing.assert_allclose(v[s], m[k][it], rtol=RTOL, atol=1e-6, err_msg=k)
    # seeds 2 and 3 are other seeds, not copies
    assert out["metrics"][-1]["td3/critic_loss"][2] != out["metrics"][-1]["td3/critic_loss"][0]


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_processes(group, cache, extra):
    port = _free_port()
    procs = [subprocess.Popen(
        [sys.executable, "-m", "dscpp_jax.cli"] + extra + [
            "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i),
            "--compile-cache", cache],
        cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)]
    outs = []
    for p in procs:
        try:
            outs.append(p.communicate(timeout=900)[0])
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            raise
    return [(p.returncode, o[-3000:]) for p, o in zip(procs, outs)]


def _run_two_processes(group, cache):
    """Two processes of one device each (one seed each): 4 iterations, then a resume to 6, so
    that the group checkpoint is written and read back as global arrays by both processes."""
    first = _two_processes(group, cache, [a if a != str(TOTAL) else "320" for a in TRAIN]
                           + ["--seeds", "0-1", "--run-dir", group])
    if any(rc for rc, _ in first):
        return first
    return _two_processes(group, cache, ["train", "--resume", group, "--total-steps", str(TOTAL),
                                         "--no-progress"])


def test_two_processes_equal_one(ref, background):
    for rc, out in background["two"].result(timeout=1800):
        assert rc == 0, out
    group = os.path.join(os.path.dirname(background["four"].result()[2]), "two")
    gj = json.load(open(os.path.join(group, "group.json")))
    assert gj["process_count"] == 2 and gj["mesh"] == {"seeds": 2}
    for s in (0, 1):
        _compare_metrics(os.path.join(ref, f"s{s}"), os.path.join(group, f"s{s}"))
        # the checkpoint both processes wrote (each its own seed) restores here, on one device
        _compare_states(load_run(os.path.join(group, f"s{s}"))[1],
                        load_run(os.path.join(ref, f"s{s}"))[1])


def _warp_config(**kw):
    """The ant U-maze on MuJoCo Warp, tiny: both Warp tests use it, so that the group programs the
    first compiles serve the second."""
    return preset("fast", "u_maze", "td3_her", physics="warp", num_envs=2, steps_per_iter=10,
                  episode_length=20, warmup_episodes=0, td3_hidden=16, td3_batch_size=16,
                  td3_updates_per_step=0.1, replay_capacity=500, eval_episodes=1,
                  inband_eval_envs=0, **kw)


def test_warp_physics_group_equals_separate_runs():
    """MuJoCo Warp's Data batches itself under vmap (its contact buffers are shared by all worlds of
    the group, not split per seed): a group of two ant seeds on Warp steps and evaluates, and each
    seed matches its separate run."""
    if not warp_available():
        pytest.skip("warp-lang is not installed")
    cfg = _warp_config()
    states = SG.init_group([0, 1], cfg)
    assert states.config.run.group_size == 2
    states, m = SG.train_step_group(states)
    assert np.asarray(m["counters/env_steps"]).tolist() == [20.0, 20.0]
    summ, _ = SG.evaluate_group(states, num_episodes=1)
    assert len(summ) == 2 and all(0.0 <= s["eval/success_rate"] <= 1.0 for s in summ)
    for i, seed in enumerate((0, 1)):
        one, _ = T.train_step(T.init(jax.random.PRNGKey(seed), cfg))
        _compare_states(SG.seed_state(states, i), one, rtol=1e-3)


def test_warp_group_seed_directory_evaluates(tmp_path):
    """A seed directory of a group trained on MuJoCo Warp restores from the group checkpoint (whose
    contact buffers are shared by the group, not split per seed) and evaluates, as `eval --run
    GROUP/s1` and `video --run GROUP/s1` do."""
    if not warp_available():
        pytest.skip("warp-lang is not installed")
    cfg = _warp_config(eval_every=0)   # the group program of the test above (eval_every: host only)
    states, group, _ = group_train.train_group(cfg, [0, 1], str(tmp_path / "g"), progress=False,
                                               max_iterations=1)
    got_cfg, one = load_run(os.path.join(group, "s1"))
    assert got_cfg.run.seed == 1
    assert_trees_equal(one.td3, SG.seed_state(states, 1).td3)
    summary, _ = evaluate(one, jax.random.PRNGKey(0), 1)
    assert 0.0 <= summary["eval/success_rate"] <= 1.0


def test_a_stuck_chain_warning_names_its_seed_once(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(host_loop, "stuck_chain_warning", lambda m, cfg, who="": (
        f"warning: {who}stuck" if cfg.run.seed == 1 else None))
    # each seed's line ends with diagnose's verdict on that seed's directory
    monkeypatch.setattr(diagnose, "chain_verdict", lambda cfg, d: f"verdict of {os.path.basename(d)}")
    assert main(TRAIN + ["--seeds", "0-1", "--run-dir", str(tmp_path / "g")]) == 0
    out, err = capsys.readouterr()
    assert err.count(": stuck") == 1 and "seed 1, iteration 1: stuck" in err
    lines = [l for l in out.splitlines() if l.startswith(("  s0:", "  s1:"))]
    assert [l.rsplit(", chain: ", 1)[1] for l in lines] == ["verdict of s0", "verdict of s1"]


def test_a_seed_finishing_early_waits_for_the_next_evaluation(tmp_path, monkeypatch):
    """A seed that reaches its budget before the others is frozen; its last row waits for the
    group's next evaluation (here the final one) instead of costing an evaluation of its own, and
    holds the numbers its separate run logs when it stops."""
    budget = {0: TOTAL, 1: TOTAL // 2}   # seed 1 stops after 3 of seed 0's 6 iterations
    monkeypatch.setattr(host_loop, "schedule_done", lambda cfg, steps, episodes: steps >= budget[cfg.run.seed])
    calls = []
    real_eval = SG.evaluate_group
    monkeypatch.setattr(SG, "evaluate_group", lambda *a, **k: calls.append(1) or real_eval(*a, **k))
    args = [a if a != "2" else "100" for a in TRAIN]   # --eval-every 100: no periodic evaluation
    group = str(tmp_path / "g")
    assert main(args + ["--seeds", "0-1", "--run-dir", group]) == 0
    assert len(calls) == 1   # the final evaluation only
    g1 = read_metrics(os.path.join(group, "s1"))
    assert g1["iteration"] == [1.0, 2.0, 3.0]
    final = json.load(open(os.path.join(group, "s1", "eval.json")))
    assert g1["eval/success_rate"][-1] == final["eval/success_rate"] and final["iteration"] == 3
    monkeypatch.setattr(SG, "evaluate_group", real_eval)
    single = str(tmp_path / "s1")
    assert main([a if a != str(TOTAL) else str(TOTAL // 2) for a in args]
                + ["--seed", "1", "--run-dir", single]) == 0
    _compare_metrics(single, os.path.join(group, "s1"))

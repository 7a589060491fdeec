"""The command line end to end on a tiny config: train, checkpoint, resume, Ctrl-C, eval, plot."""
import csv
import json
import os
import shutil
import signal
import subprocess
import sys

import jax
import pytest
from jax._src import xla_bridge

from dscpp_jax import diagnose
from dscpp_jax import checkpoint as ck
from dscpp_jax import trainer as T
from dscpp_jax.cli import build_parser, deterministic_default, main
from dscpp_jax.config import preset
from dscpp_jax.envs import ant_maze
from dscpp_jax.host_loop import frontier_note, medium_td3_note, notes_beyond_paper
from dscpp_jax.plots import _group_runs, plot_curves
from dscpp_jax.options import STATUS_NAMES
from dscpp_jax.run_logging import (OPTIONS_FILE, RunLogger, _git_commit, load_config, read_metrics,
                                   read_startup, write_config)
from dscpp_jax.runtime import (DETERMINISTIC_FLAG, FUSION_AUTOTUNER_FLAG, use_compile_cache,
                               use_deterministic_ops, use_fusion_autotuner_off, use_xla_flags)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

TINY = ["num_envs=4", "steps_per_iter=20", "episode_length=100", "warmup_episodes=2",
        "max_options=4", "max_pos_traj=8", "max_neg=8", "buffer_len=10", "option_timeout=40",
        "gestation=2", "td3_hidden=32", "td3_batch_size=32", "td3_updates_per_step=0.1",
        "replay_capacity=2000", "model_capacity=2000", "dyn_hidden=16", "dyn_batch_size=32",
        "dyn_updates_per_step=0.05", "dyn_pretrain_steps=5", "mpc_samples=32", "mpc_horizon=3",
        "eval_episodes=2"]


def _sets(extra=()):
    out = []
    for s in list(TINY) + list(extra):
        out += ["--set", s]
    return out


def test_cli_train_resume_interrupt_eval_plot(tmp_path, monkeypatch, capsys):
    run = str(tmp_path / "run")
    rc = main(["train", "--env", "point_u_maze", "--algo", "mb_dscpp", "--seed", "0",
               "--run-dir", run, "--total-steps", "160", "--eval-every", "1",
               "--checkpoint-every", "1", "--no-progress"] + _sets())
    assert rc == 0
    cfg = json.load(open(os.path.join(run, "config.json")))
    assert cfg["config"]["algo"] == "mb_dscpp" and "jax" in cfg["versions"]
    assert "xla_flags" in cfg["versions"]
    # the env's own constants are recorded too (physics settings of the ant, for instance)
    assert cfg["env"]["episode_length"] == cfg["config"]["task"]["episode_length"]
    m = read_metrics(run)
    assert m["iteration"] == [1.0, 2.0]
    assert m["eval/success_rate"][-1] == m["eval/success_rate"][-1]  # evaluated (not NaN)
    assert ck.latest_step(run) == 2
    assert any(f.startswith("events") for f in os.listdir(os.path.join(run, "tb")))
    # the final evaluation is saved, as a seed group saves each seed's
    final = json.load(open(os.path.join(run, "eval.json")))
    assert final["iteration"] == 2 and final["seed"] == 0 and final["env_steps"] == 160
    assert 0.0 <= final["eval/success_rate"] <= 1.0
    # the start-up is recorded: one record per command, up to its first iteration
    st = read_startup(run)
    assert len(st) == 1 and st[0]["resumed_at_iteration"] == 0 and st[0]["iteration"] == 1
    assert {"init", "first iteration"} <= set(st[0]["phases_s"])
    assert st[0]["command_to_first_iteration_s"] >= sum(st[0]["phases_s"].values()) - 1e-2
    # and the run's last line says why its chain ends where it does (diagnose's verdict)
    out = capsys.readouterr().out
    verdict = diagnose.diagnose_run(run)["verdict"]
    assert f"chain: {verdict} (python -m dscpp_jax.cli diagnose {run})" in out

    # resume continues from iteration 2; Ctrl-C during iteration 4 saves and exits cleanly
    calls = {"n": 0}
    real = T.train_step

    def interrupting(state):
        calls["n"] += 1
        if calls["n"] == 2:
            signal.raise_signal(signal.SIGINT)
        return real(state)

    monkeypatch.setattr(T, "train_step", interrupting)
    rc = main(["train", "--resume", run, "--total-steps", "400", "--no-progress"])
    assert rc == 0
    assert ck.latest_step(run) == 4
    assert read_metrics(run)["iteration"] == [1.0, 2.0, 3.0, 4.0]
    st = read_startup(run)
    assert len(st) == 2 and st[1]["resumed_at_iteration"] == 2 and st[1]["iteration"] == 3
    assert "restore" in st[1]["phases_s"]
    monkeypatch.setattr(T, "train_step", real)
    rc = main(["train", "--resume", run, "--total-steps", "400", "--no-progress"])
    assert rc == 0 and ck.latest_step(run) == 5
    assert read_metrics(run)["env_steps"][-1] == 400
    assert main(["train", "--resume", run, "--set", "num_envs=8"]) == 2
    # an episode budget stops the run before its step budget (4 envs finish an episode every
    # 100 steps each: 4 episodes by 400 env steps, 8 by 800)
    assert read_metrics(run)["episodes"][-1] == 4
    rc = main(["train", "--resume", run, "--total-steps", "4000", "--total-episodes", "8",
               "--no-progress"])
    assert rc == 0
    m = read_metrics(run)
    assert m["episodes"][-1] == 8 and m["env_steps"][-1] == 800

    # the option table every OPTIONS_EVERY iterations, one line per row in use, each snapshot
    # once across the resumes (the interrupted chunk's rows past its checkpoint were dropped);
    # the last one is the chain of the final checkpoint
    with open(os.path.join(run, OPTIONS_FILE), newline="") as f:
        table = list(csv.DictReader(f))
    assert sorted({int(r["iteration"]) for r in table}) == [5, 10]
    last = [r for r in table if r["iteration"] == "10"]
    assert len({r["option"] for r in last}) == len(last)
    run_cfg = load_config(run)
    state = ck.restore_state(run, T.init(jax.random.PRNGKey(run_cfg.run.seed), run_cfg), step=10)
    chain = state.chain
    in_use = [k for k in range(chain.status.shape[0]) if int(chain.status[k]) != 0]
    assert [int(r["option"]) for r in last] == in_use
    for r in last:
        k = int(r["option"])
        assert r["status"] == STATUS_NAMES[int(chain.status[k])]
        assert [int(r[c]) for c in ("parent", "executions", "successes", "positives",
                                    "negatives")] == [int(chain.parent[k]),
                                                      int(chain.executions[k]),
                                                      int(chain.successes[k]),
                                                      int(chain.pos_count[k]),
                                                      int(chain.neg_count[k])]

    assert main(["eval", "--run", run, "--episodes", "2"]) == 0
    ev = json.load(open(os.path.join(run, "eval.json")))
    assert 0.0 <= ev["eval/success_rate"] <= 1.0 and ev["iteration"] == 10
    assert os.path.exists(os.path.join(run, "eval_trajectory.png"))
    assert main(["eval", "--run", run, "--starts", "8,8;0,4", "--no-plot"]) == 0
    assert len(json.load(open(os.path.join(run, "eval_starts.json")))["steps_per_start"]) == 2
    # other kinds of evaluation never overwrite eval.json
    assert main(["eval", "--run", run, "--episodes", "2", "--explore", "--no-plot"]) == 0
    assert json.load(open(os.path.join(run, "eval_explore.json")))["explore"] is True
    assert main(["eval", "--run", run, "--episodes", "2", "--step", "9", "--no-plot"]) == 0
    assert json.load(open(os.path.join(run, "eval_step9.json")))["iteration"] == 9
    assert json.load(open(os.path.join(run, "eval.json"))) == ev

    assert main(["plot", run]) == 0
    for f in ("curves.png", "trajectory.png", "classifiers.png"):
        assert os.path.getsize(os.path.join(run, "plots", f)) > 1000
    out = str(tmp_path / "cmp")
    assert main(["plot", run, run, "--out", out, "--curves-only"]) == 0
    assert os.path.exists(os.path.join(out, "curves.png"))
    assert os.path.getsize(os.path.join(out, "seeds.png")) > 1000   # one panel per run
    regions = str(tmp_path / "regions")
    assert main(["plot", run, "--out", regions, "--regions-only"]) == 0
    assert sorted(os.listdir(regions)) == ["classifiers.png", "curves.png"]


def test_cli_rejects_bad_input(tmp_path, capsys):
    assert main(["train", "--env", "no_such_maze", "--run-dir", str(tmp_path / "x")]) == 2
    assert "valid names" in capsys.readouterr().err
    assert main(["train", "--set", "gestation=0", "--run-dir", str(tmp_path / "y")]) == 2
    assert "gestation" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "--algo", "ppo"])


def test_metrics_csv_widens_for_late_columns(tmp_path):
    log = RunLogger(str(tmp_path), tensorboard=False)
    log.log({"iteration": 1, "env_steps": 10, "train/x": 1.0})
    log.log({"iteration": 2, "env_steps": 20, "train/x": 2.0, "eval/success_rate": 0.5})
    log.close()
    m = read_metrics(str(tmp_path))
    assert m["train/x"] == [1.0, 2.0]
    assert m["eval/success_rate"][1] == 0.5 and m["eval/success_rate"][0] != m["eval/success_rate"][0]
    # resuming from iteration 1 drops the later row
    RunLogger(str(tmp_path), resume_iteration=1, tensorboard=False).close()
    assert read_metrics(str(tmp_path))["iteration"] == [1.0]


def test_plot_groups_seeds_and_names_variants(tmp_path):
    runs = {}
    for name, kw in {"a0": dict(seed=0), "a1": dict(seed=1),
                     "b0": dict(seed=0, td3_batch_size=1024, total_env_steps=5),
                     "c0": dict(seed=0, algo="mf_dscpp")}.items():
        runs[name] = str(tmp_path / name)
        os.makedirs(runs[name])
        kw = dict(kw)
        algo = kw.pop("algo", "mb_dscpp")
        write_config(runs[name], preset("fast", "u_maze", algo, **kw).to_dict())
    groups = _group_runs([runs[k] for k in ("a0", "a1", "b0", "c0")])
    assert groups == {"u_maze mb_dscpp td3_batch_size=256": [runs["a0"], runs["a1"]],
                      "u_maze mb_dscpp td3_batch_size=1024": [runs["b0"]],
                      "u_maze mf_dscpp": [runs["c0"]]}
    # a run written before a field existed used that field's default: it is named by it
    old = str(tmp_path / "old")
    os.makedirs(old)
    cfg = preset("fast", "u_maze", "mb_dscpp", td3_clip_targets=False).flat()   # a flat, older file
    del cfg["td3_clip_targets"]
    write_config(old, cfg)
    groups = _group_runs([runs["a0"], runs["a1"], old])
    assert groups == {"u_maze mb_dscpp td3_clip_targets=True": [runs["a0"], runs["a1"]],
                      "u_maze mb_dscpp td3_clip_targets=False": [old]}
    # runs that recorded different env settings (physics) are told apart by them
    soft, stiff = str(tmp_path / "soft"), str(tmp_path / "stiff")
    for r, solimp in ((soft, "0.8 0.8 0.01"), (stiff, "0.9 0.95 0.001")):
        os.makedirs(r)
        write_config(r, preset("fast", "u_maze", "mb_dscpp").to_dict(),
                     {"env": {"contact_solimp": solimp, "episode_length": 1000}})
    assert _group_runs([soft, stiff]) == {
        "u_maze mb_dscpp env.contact_solimp=0.8 0.8 0.01": [soft],
        "u_maze mb_dscpp env.contact_solimp=0.9 0.95 0.001": [stiff]}


def test_plot_curves_takes_labels(tmp_path):
    runs = []
    for k in range(3):
        r = tmp_path / f"r{k}"
        os.makedirs(r)
        write_config(str(r), preset("fast", "u_maze", "mb_dscpp", seed=k).to_dict())
        with open(r / "metrics.csv", "w") as f:
            f.write("iteration,env_steps,episodes,wall_clock,eval/success_rate\n")
            for i in range(1, 4):
                f.write(f"{i},{100 * i},{10 * i},{i},{0.1 * i * (k + 1)}\n")
        runs.append(str(r))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    seen = {}
    orig = plt.Axes.plot

    def spy(self, *a, **kw):
        seen.setdefault(kw.get("label"), 0)
        seen[kw.get("label")] += 1
        return orig(self, *a, **kw)
    plt.Axes.plot = spy
    try:
        path = plot_curves([f"before={runs[0]}", f"after, x=1={runs[1]}", f"after, x=1={runs[2]}"],
                           str(tmp_path / "c.png"))
    finally:
        plt.Axes.plot = orig
    assert os.path.exists(path)
    assert "before (n=1)" in seen and "after, x=1 (n=2)" in seen
    with pytest.raises(ValueError, match="not a run directory"):
        plot_curves([f"a={tmp_path / 'nope'}"], str(tmp_path / "d.png"))


def test_config_records_the_git_commit_only_of_a_checkout_that_tracks_the_source(tmp_path):
    """config.json's `dscpp_jax_git`: HEAD (+dirty once a tracked file changes) of the checkout
    that tracks the source file, nothing for a copy outside one."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")

    def git(*args):
        return subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c",
                               "user.email=t@t", *args], capture_output=True, text=True,
                              check=True).stdout.strip()
    src = tmp_path / "mod.py"
    src.write_text("x = 1\n")
    git("init", "-q")
    assert _git_commit(str(src)) == ""  # untracked
    git("add", "mod.py")
    git("commit", "-q", "-m", "init")
    head = git("rev-parse", "HEAD")
    assert _git_commit(str(src)) == head
    src.write_text("x = 2\n")
    assert _git_commit(str(src)) == head + "+dirty"
    outside = tmp_path.parent / "outside_mod.py"
    outside.write_text("x = 1\n")
    assert _git_commit(str(outside)) == ""


def test_deterministic_switch_sets_xla_flags_only_before_jax_uses_a_device(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    assert not use_deterministic_ops(False) and os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"
    assert use_deterministic_ops(True)
    assert os.environ["XLA_FLAGS"] == f"--xla_dump_to=/tmp/x {DETERMINISTIC_FLAG}"
    assert use_deterministic_ops(True)                 # already there: not added twice
    assert os.environ["XLA_FLAGS"].count("deterministic") == 1
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: True)
    assert not use_deterministic_ops(True) and os.environ["XLA_FLAGS"] == ""   # too late: unchanged
    p = build_parser()
    assert p.parse_args(["train"]).deterministic is None               # the default: chosen
    assert p.parse_args(["train", "--deterministic"]).deterministic is True
    assert p.parse_args(["train", "--no-deterministic"]).deterministic is False
    assert p.parse_args(["eval", "--run", "r", "--no-deterministic"]).deterministic is False


def test_fusion_autotuner_flag_is_added_once_and_never_over_the_users_choice(monkeypatch):
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    assert use_xla_flags(False) is False
    assert os.environ["XLA_FLAGS"] == f"--xla_dump_to=/tmp/x {FUSION_AUTOTUNER_FLAG}"
    assert use_xla_flags(True)                          # added once; determinism on top
    assert os.environ["XLA_FLAGS"] == (f"--xla_dump_to=/tmp/x {FUSION_AUTOTUNER_FLAG} "
                                       f"{DETERMINISTIC_FLAG}")
    on = "--xla_gpu_experimental_enable_fusion_autotuner=true"
    monkeypatch.setenv("XLA_FLAGS", on)                 # the user's choice stands
    assert not use_fusion_autotuner_off() and os.environ["XLA_FLAGS"] == on
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: True)
    assert not use_fusion_autotuner_off() and os.environ["XLA_FLAGS"] == ""   # too late
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    assert use_fusion_autotuner_off() and os.environ["XLA_FLAGS"] == FUSION_AUTOTUNER_FLAG


def test_xla_accepts_the_fusion_autotuner_flag():
    """XLA aborts on a flag it does not know; this jaxlib must parse the one `train` adds."""
    env = dict(os.environ, XLA_FLAGS=FUSION_AUTOTUNER_FLAG, JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, "-c", "import jax.numpy as j; print(j.ones(2).sum())"],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "2.0", r.stderr[-2000:]


def test_deterministic_default_follows_the_physics(tmp_path, monkeypatch):
    """Deterministic XLA kernels by default, except where the ant runs on MuJoCo Warp (which does
    not repeat either way), for every learner: the physics from --physics, --set physics=, or the
    saved config of --resume and --run ("auto" means Warp where warp-lang is installed).
    Point-mass twins stay deterministic."""
    p = build_parser()

    def default(*argv):
        return deterministic_default(p.parse_args(list(argv)))

    for algo in ("mf_dscpp", "td3_her", "dsc", "mb_dscpp", "mb_flat", "mb_flat_value"):
        a = ("--algo", algo)
        assert default("train", "--env", "point_u_maze", "--physics", "warp", *a)
        assert default("train", "--env", "u_maze", "--physics", "jax", *a)
        assert not default("train", "--env", "u_maze", "--physics", "warp", *a)
        assert not default("train", "--env", "u_maze", "--set", "physics=warp", *a)
        assert not default("train", "--env", "u_maze", "--physics", "warp", *a, "--seeds", "0-15")
        assert default("train", "--env", "u_maze", "--physics", "jax", "--set", "physics=warp", *a)
    assert not default("train", "--env", "u_maze", "--physics", "warp")   # --algo's default
    for installed in (True, False):
        monkeypatch.setattr(ant_maze, "warp_available", lambda: installed)
        assert default("train", "--env", "u_maze") is not installed           # physics auto
        assert default("train", "--env", "four_rooms", "--physics", "auto") is not installed
    for physics, algo, det in (("warp", "mf_dscpp", False), ("jax", "mf_dscpp", True),
                               ("warp", "mb_dscpp", False), ("jax", "mb_dscpp", True)):
        run = tmp_path / f"{physics}_{algo}"
        run.mkdir()
        (run / "config.json").write_text(json.dumps({"config": {
            "env": "u_maze", "physics": physics, "algo": algo}}))
        assert default("eval", "--run", str(run)) is det
        assert default("video", "--run", str(run)) is det
        assert default("train", "--resume", str(run)) is det     # the saved physics
        assert default("train", "--resume", str(run), "--physics", "jax")
    group = tmp_path / "group"
    group.mkdir()
    (group / "group.json").write_text(json.dumps({"seeds": [0, 1], "config": {
        "env": "medium", "physics": "warp", "algo": "mb_dscpp"}}))
    assert not default("train", "--resume", str(group))
    assert default("train", "--resume", str(group), "--physics", "jax")


def test_compile_cache_stores_programs_and_a_second_process_loads_them(tmp_path):
    """A fresh process with the cache compiles and stores; the next one loads from it."""
    cache = tmp_path / "cache"
    code = (
        "import sys, jax, jax.numpy as jnp\n"
        "from jax._src import monitoring\n"
        "from dscpp_jax.runtime import use_compile_cache\n"
        "hits = []\n"
        "monitoring.register_event_listener(\n"
        "    lambda name, **kw: hits.append(name) if name.endswith('cache_hits') else None)\n"
        f"assert use_compile_cache({str(cache)!r}, min_compile_time_s=0.0) == {str(cache)!r}\n"
        "f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + 7.0)\n"
        "f(jnp.ones((16, 16))).block_until_ready()\n"
        "print('hits', len(hits))\n")
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("DSCPP_JAX_COMPILE_CACHE", None)
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                           cwd=ROOT, timeout=300) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    assert any(cache.iterdir())                                  # the first process stored it
    assert "hits 0" in runs[0].stdout and "hits 0" not in runs[1].stdout
    assert use_compile_cache("off") is None and use_compile_cache("") is None
    assert build_parser().parse_args(["train", "--compile-cache", "d"]).compile_cache == "d"
    assert build_parser().parse_args(["eval", "--run", "r"]).compile_cache is None


def test_train_names_the_chains_frontier_where_the_preset_turns_it_on():
    note = frontier_note(preset("fast", "medium", "mb_dscpp"))
    assert "frontier_start_prob=0.5" in note and "frontier_parent=true" in note
    assert "--set frontier_start_prob=0 --set frontier_parent=false" in note
    assert frontier_note(preset("fast", "u_maze", "mb_dscpp")) == ""
    assert frontier_note(preset("fast", "medium", "td3_her")) == ""
    assert frontier_note(preset("fast", "medium", "mf_dscpp", frontier_start_prob=0.0,
                                frontier_parent=False)) == ""


def test_train_names_the_medium_mazes_model_free_td3():
    """A model-free run on the ant medium maze says that its TD3 (HER future at 0.8, action
    penalty 2) is beyond the paper and how to get the other mazes' TD3; nothing for the
    model-based learners, the other mazes, or a user who set the TD3 back."""
    for algo in ("mf_dscpp", "td3_her"):
        note = medium_td3_note(preset("fast", "medium", algo))
        assert "her_strategy=future, her_relabel_prob=0.8, td3_action_l2=2" in note, algo
        assert "--set her_strategy=final --set her_relabel_prob=0.5 --set td3_action_l2=1" in note
    assert medium_td3_note(preset("fast", "medium", "mb_dscpp")) == ""
    assert notes_beyond_paper(preset("fast", "medium", "dsc")) == []    # the paper's baseline
    assert medium_td3_note(preset("fast", "u_maze", "mf_dscpp")) == ""
    assert medium_td3_note(preset("fast", "medium", "mf_dscpp", her_strategy="final")) == ""
    assert len(notes_beyond_paper(preset("fast", "medium", "mf_dscpp"))) == 2
    assert len(notes_beyond_paper(preset("fast", "medium", "td3_her"))) == 1
    assert notes_beyond_paper(preset("fast", "u_maze", "mf_dscpp")) == []

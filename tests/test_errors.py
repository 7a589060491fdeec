"""What a user meets when something is wrong: missing, foreign or damaged run directories, configs
from other versions, bad `--set` values, a full disk or a read-only directory, damaged
checkpoints, the Python API and env constructors called with bad arguments. Each must end in one
`error: ...` line (exit code 2) that names the fix, and never lose what was saved."""
import errno
import json
import os
import re
import shutil
import subprocess
import sys
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscpp_jax
from dscpp_jax import envs, plots
from dscpp_jax import checkpoint as ck
from dscpp_jax import config as C
from dscpp_jax import run_logging as RL
import dscpp_jax.cli as cli
from dscpp_jax.cli import main
from dscpp_jax.config import parse_value, preset
from dscpp_jax.run_dir import load_run
from dscpp_jax.run_logging import RunLogger, load_config, read_metrics, write_config

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# the flat TD3+HER learner on the point-mass U-maze, a few tiny iterations: the cheapest program
# that goes through every step of the command line
TINY = ["num_envs=2", "steps_per_iter=10", "episode_length=40", "warmup_episodes=1",
        "buffer_len=10", "option_timeout=20", "td3_hidden=16", "td3_batch_size=16",
        "td3_updates_per_step=0.1", "replay_capacity=400", "model_capacity=400",
        "eval_episodes=2"]


def _train_args(run, total=40, extra=()):
    args = ["train", "--env", "point_u_maze", "--algo", "td3_her", "--run-dir", run,
            "--total-steps", str(total), "--eval-every", "0", "--checkpoint-every", "1",
            "--no-progress"]
    for s in TINY + list(extra):
        args += ["--set", s]
    return args


def _one_error_line(err: str) -> str:
    lines = [l for l in err.strip().splitlines() if l.startswith("error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def _snapshot(run):
    """Every file under the run directory with its bytes (to show nothing saved was lost)."""
    out = {}
    for root, _, files in os.walk(run):
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, run)] = fh.read()
    return out


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny run with checkpoints at iterations 1 and 2 (keep_checkpoints=2)."""
    run = str(tmp_path_factory.mktemp("runs") / "run")
    assert main(_train_args(run)) == 0
    assert ck.latest_step(run) == 2
    return run


def _copy(trained, tmp_path, name="run"):
    dst = str(tmp_path / name)
    shutil.copytree(trained, dst)
    return dst


# ------------------------------------------------------------------------------------------------
# run directories that are missing, foreign or from another version
# ------------------------------------------------------------------------------------------------
def test_missing_and_foreign_run_directories_get_one_line_errors(tmp_path, capsys):
    missing = str(tmp_path / "nope")
    for argv in (["train", "--resume", missing], ["eval", "--run", missing],
                 ["plot", missing, "--curves-only"]):
        assert main(argv) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert missing in line and ("does not exist" in line or "not a run directory" in line)
    assert main(["train", "--resume", missing]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "config.json" in line and "metrics.csv" in line and "checkpoints/" in line

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("hello")
    for argv in (["eval", "--run", str(foreign)], ["plot", str(foreign), "--curves-only"]):
        assert main(argv) == 2
        assert "no config.json" in _one_error_line(capsys.readouterr().err)

    (foreign / "config.json").write_text("{not json")
    assert main(["train", "--resume", str(foreign)]) == 2
    assert "not valid JSON" in _one_error_line(capsys.readouterr().err)
    (foreign / "config.json").write_text(json.dumps({"something": 1}))
    assert main(["eval", "--run", str(foreign)]) == 2
    assert 'no "config" section' in _one_error_line(capsys.readouterr().err)
    # a run directory whose config is fine but that never saved a checkpoint
    write_config(str(foreign), preset("fast", "point_u_maze", "td3_her").to_dict())
    assert main(["eval", "--run", str(foreign)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "no checkpoint" in line and "check the disk" not in line
    # a seed of a committed seed group (results keep no checkpoints): says so, not "the disk"
    lean = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "experiments",
                        "results", "paper", "runs", "u_maze-dsc-g0-4")
    shutil.copytree(lean, tmp_path / "lean")
    assert main(["eval", "--run", str(tmp_path / "lean" / "s0"), "--episodes", "1"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "copy without checkpoints" in line and "check the disk" not in line


def test_config_from_another_version(tmp_path, monkeypatch, capsys):
    run = str(tmp_path / "old")
    os.makedirs(run)
    cfg = preset("fast", "point_u_maze", "td3_her")
    d = cfg.to_dict()
    write_config(run, d)
    payload = json.load(open(os.path.join(run, "config.json")))
    assert payload["config_defaults"]["chain"]["gestation"] == C.Config().chain.gestation   # recorded for later

    # a field this version no longer has, at the value that meant "off": ignored quietly
    monkeypatch.setattr(C, "RETIRED_FIELDS", {"old_knob": 0.0})
    payload = {"config": {**d, "old_knob": 0.0}}          # written before defaults were recorded
    json.dump(payload, open(os.path.join(run, "config.json"), "w"))
    assert load_config(run) == cfg
    # ... and set to something else: a clear error naming the field and its "off" value
    payload["config"]["old_knob"] = 0.5
    json.dump(payload, open(os.path.join(run, "config.json"), "w"))
    assert main(["eval", "--run", run]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "older" in line and "old_knob=0.5" in line and "off: 0.0" in line
    # the default recorded beside the run decides where the registry does not know the field
    payload = {"config": {**d, "newer_knob": 3}, "config_defaults": {"newer_knob": 3}}
    json.dump(payload, open(os.path.join(run, "config.json"), "w"))
    assert load_config(run) == cfg
    payload["config"]["newer_knob"] = 4
    json.dump(payload, open(os.path.join(run, "config.json"), "w"))
    assert main(["train", "--resume", run]) == 2
    assert "newer_knob=4" in _one_error_line(capsys.readouterr().err)
    # a field with no known default at all cannot be judged: refused, named
    payload = {"config": {**d, "mystery": 1}}
    json.dump(payload, open(os.path.join(run, "config.json"), "w"))
    with pytest.raises(ValueError, match="mystery=1"):
        load_config(run)


def test_set_names_the_field_its_type_and_an_example(capsys):
    assert main(["train", "--set", "gestation=abc"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "gestation" in line and "an integer" in line and "e.g. --set gestation=" in line
    with pytest.raises(ValueError, match="td3_lr is a number, e.g. --set td3_lr="):
        parse_value("td3_lr", "fast")
    with pytest.raises(ValueError, match="diverse_starts is true or false"):
        parse_value("diverse_starts", "maybe")
    with pytest.raises(ValueError, match="gestation is an integer"):
        parse_value("gestation", "2.5")
    assert parse_value("gestation", "1e3") == 1000 and parse_value("td3_lr", "3e-4") == 3e-4
    assert main(["eval", "--run", "r", "--starts", "1,2;3"]) == 2
    assert "--starts expects x,y pairs" in _one_error_line(capsys.readouterr().err)
    # negative cadences and seeds were taken as they came
    for argv, says in ((["--eval-every", "-2"], "eval_every=-2 must be >= 0"),
                       (["--checkpoint-every", "-1"], "checkpoint_every=-1 must be >= 0"),
                       (["--seed", "-1"], "seed=-1 must be >= 0"),
                       (["--set", "keep_checkpoints=0"], "keep_checkpoints=0 must be >= 1")):
        assert main(["train", "--env", "point_u_maze"] + argv) == 2
        assert says in _one_error_line(capsys.readouterr().err)
    # a time budget of 0 or less would stop after one iteration without a word
    for bad, says in (("-1", "-1: give a number of seconds > 0"), ("0", "0: give a number"),
                      ("soon", "'soon' is not a number of seconds")):
        with pytest.raises(SystemExit) as e:
            main(["train", "--env", "point_u_maze", "--time-budget", bad])
        assert e.value.code == 2 and says in capsys.readouterr().err


def test_plot_of_a_results_group_draws_its_seeds_curves(tmp_path, capsys):
    # a committed seed group (no checkpoints): the group directory stands for its seeds, their
    # curves are drawn, and each seed says in one line why there is nothing more
    lean = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "experiments",
                        "results", "paper", "runs", "u_maze-dsc-g0-4")
    group = str(tmp_path / "group")
    shutil.copytree(lean, group)
    out = str(tmp_path / "plots")
    assert main(["plot", group, "--out", out]) == 0
    captured = capsys.readouterr()
    assert os.path.getsize(os.path.join(out, "curves.png")) > 1000
    assert sorted(os.listdir(out)) == ["curves.png", "seeds.png"]   # and one panel per seed
    notes = [l for l in captured.err.splitlines() if "no checkpoint, so only its curves" in l]
    assert [l.split(":")[0] for l in notes] == [os.path.join(group, f"s{s}") for s in range(5)]


# ------------------------------------------------------------------------------------------------
# damaged checkpoints, a full disk, a read-only directory
# ------------------------------------------------------------------------------------------------
def _damage(run, step):
    path = os.path.join(run, "checkpoints", str(step), "default", "_METADATA")
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def test_damaged_newest_checkpoint_falls_back_loudly(trained, tmp_path, capsys):
    run = _copy(trained, tmp_path)
    _damage(run, 2)
    assert main(["eval", "--run", run, "--episodes", "2", "--no-plot"]) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "iteration 2" in err and "Using iteration 1" in err
    assert json.load(open(os.path.join(run, "eval.json")))["iteration"] == 1
    assert ck.all_steps(run) == [1, 2]           # eval changes nothing in the run

    # resume: starts from iteration 1, sets the damaged one aside, writes iteration 2 again
    assert main(["train", "--resume", run, "--total-steps", "60", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "Using iteration 1" in err and "resumed" in err
    assert ck.all_steps(run) == [2, 3]
    assert os.listdir(os.path.join(run, ck.UNRESTORABLE_DIR))[0].startswith("2-")
    assert read_metrics(run)["iteration"] == [1.0, 2.0, 3.0]

    # nothing restores: a clear error, no traceback
    for s in ck.all_steps(run):
        _damage(run, s)
    assert main(["eval", "--run", run]) == 2
    assert "no checkpoint under" in _one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize("where,err,expect", [
    ("metrics", errno.ENOSPC, "is full"),
    ("checkpoint", errno.ENOSPC, "is full"),
    ("metrics", errno.EROFS, "not writable"),
])
def test_full_disk_or_read_only_run_directory(trained, tmp_path, monkeypatch, capsys, where, err,
                                              expect):
    run = _copy(trained, tmp_path)
    before = _snapshot(run)
    calls = {"n": 0}

    def fail(*a, **k):
        calls["n"] += 1
        raise OSError(err, os.strerror(err))
    if where == "metrics":
        monkeypatch.setattr(RunLogger, "log", fail)
    else:
        monkeypatch.setattr(ck.ocp.CheckpointManager, "save", fail)
    assert main(["train", "--resume", run, "--total-steps", "80", "--no-progress"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert calls["n"] >= 1 and expect in line and f"--resume {run}" in line
    after = _snapshot(run)
    # everything saved before is still there: config and checkpoints byte for byte, metrics.csv
    # and startup.jsonl at most with lines appended (a resume drops rows past its checkpoint)
    for k, v in before.items():
        if k in ("metrics.csv", "startup.jsonl"):
            assert after[k].startswith(v)
        elif not k.startswith("tb"):
            assert after[k] == v, k
    assert ck.all_steps(run) == [1, 2]


def test_eval_into_a_read_only_run_directory(trained, tmp_path, monkeypatch, capsys):
    run = _copy(trained, tmp_path)

    def read_only_open(path, mode="r", *a, **k):
        if "w" in mode:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), path)
        return open(path, mode, *a, **k)
    monkeypatch.setattr(cli, "open", read_only_open, raising=False)
    assert main(["eval", "--run", run, "--episodes", "2", "--no-plot"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "eval.json" in line and "not writable" in line


def test_checkpoint_save_keeps_older_ones_until_the_new_one_reads_back(tmp_path, monkeypatch,
                                                                       capsys):
    run = str(tmp_path)
    tree = {"a": jnp.arange(4.0)}
    c = ck.Checkpointer(run, keep=1)
    c.save(1, tree)
    c.save(2, tree)
    assert c.all_steps() == [2]                      # keep=1 prunes once the new one reads back
    # a new checkpoint that does not read back: set aside, the older one stays
    monkeypatch.setattr(ck.Checkpointer, "_read_back",
                        lambda self, step, like: (_ for _ in ()).throw(ValueError("Invalid JSON")))
    with pytest.raises(ck.CheckpointError, match="did not read back.*iterations \\[2\\]\\) were kept"):
        c.save(3, tree)
    assert c.all_steps() == [2]
    assert os.listdir(os.path.join(run, ck.UNRESTORABLE_DIR))[0].startswith("3-")
    # a save that dies half-way (full disk): the older one stays, the error names the fix
    monkeypatch.undo()
    monkeypatch.setattr(ck.ocp.CheckpointManager, "save",
                        lambda *a, **k: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space")))
    with pytest.raises(ck.CheckpointError, match="is full"):
        c.save(4, tree)
    c.close()
    assert ck.all_steps(run) == [2]
    assert float(ck.restore_state(run, tree)["a"][3]) == 3.0


def test_metrics_csv_survives_a_failed_rewrite_and_a_cut_row(tmp_path, monkeypatch):
    log = RL.RunLogger(str(tmp_path), tensorboard=False)
    log.log({"iteration": 1, "env_steps": 10, "train/x": 1.0})
    text = open(tmp_path / "metrics.csv").read()
    monkeypatch.setattr(RL.os, "fsync", lambda fd: (_ for _ in ()).throw(
        OSError(errno.ENOSPC, "No space left on device")))
    with pytest.raises(OSError):
        log.log({"iteration": 2, "env_steps": 20, "train/x": 2.0, "eval/success_rate": 0.5})
    monkeypatch.undo()
    assert open(tmp_path / "metrics.csv").read() == text   # the widening rewrite left it whole
    assert [f for f in os.listdir(tmp_path) if f.startswith(".metrics")] == []
    with open(tmp_path / "metrics.csv", "a") as f:
        f.write("2,2")                                     # a row cut short by a full disk
    RL.RunLogger(str(tmp_path), resume_iteration=5, tensorboard=False).close()
    assert read_metrics(str(tmp_path))["iteration"] == [1.0]


# ------------------------------------------------------------------------------------------------
# the Python API and the env constructors
# ------------------------------------------------------------------------------------------------
def test_python_api_and_env_constructors_reject_bad_arguments(trained):
    cfg, state = load_run(trained)
    with pytest.raises(TypeError, match="needs a dscpp_jax.Config"):
        dscpp_jax.init(cfg, jax.random.PRNGKey(0))       # arguments swapped
    with pytest.raises(TypeError, match="needs a PRNG key"):
        dscpp_jax.init(0, cfg)
    with pytest.raises(ValueError, match="gestation"):
        dscpp_jax.init(jax.random.PRNGKey(0), cfg.override(gestation=0))
    with pytest.raises(TypeError, match="TrainState"):
        dscpp_jax.train_step({"not": "a state"})
    with pytest.raises(TypeError, match="TrainState"):
        dscpp_jax.evaluate(cfg)
    with pytest.raises(ValueError, match="shape \\(N, 2\\)"):
        dscpp_jax.evaluate(state, starts=[[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError, match="num_episodes must be >= 1"):
        dscpp_jax.evaluate(state, num_episodes=-1)
    with pytest.raises(ValueError, match="episode_length must be > 0"):
        envs.make("point_u_maze", episode_length=0)
    with pytest.raises(ValueError, match="episode_length must be int"):
        envs.make("point_u_maze", episode_length="100")
    with pytest.raises(ValueError, match="goal_tolerance must be > 0"):
        envs.make_from_map("1111\n1rg1\n1111", 2.0, robot="point", goal_tolerance=-1.0)
    with pytest.raises(ValueError, match="unknown character"):
        envs.make_from_map("1111\n1rx1\n1111", 2.0, robot="point")
    assert envs.make("point_u_maze", goal_tolerance=1).config.goal_tolerance == 1


# ------------------------------------------------------------------------------------------------
# the optional Warp probe of MuJoCo MJX, the trajectory plot's legend
# ------------------------------------------------------------------------------------------------
def test_missing_warp_probe_is_silent_other_output_is_not(tmp_path):
    """With `warp` not importable, importing the package prints no Warp notice; the probe itself
    still runs (a reload shows it) and other lines printed during the import pass through."""
    (tmp_path / "sitecustomize.py").write_text(
        "import sys\n"
        "class _NoWarp:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'warp' or name.startswith('warp.'):\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, _NoWarp())\n")
    (tmp_path / "chatty_mod.py").write_text(
        "print(\"Failed to import warp: No module named 'warp'\")\n"
        "print('Failed to import warp: CUDA driver too old')\n"
        "print('hello from chatty_mod')\n")
    code = ("import importlib, sys\n"
            "import dscpp_jax\n"
            "print('IMPORTED', flush=True)\n"
            "from dscpp_jax.envs._quiet_import import import_quietly\n"
            "import_quietly('chatty_mod')\n"
            "import mujoco.mjx.warp as w\n"
            "importlib.reload(w)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), ROOT]),
           "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    before, _, after = (r.stdout + r.stderr).partition("IMPORTED")
    assert "Failed to import" not in before
    assert "Failed to import warp: CUDA driver too old" in after
    assert "hello from chatty_mod" in after
    assert after.count("No module named 'warp'") == 2     # the reload's probe, not silenced


def test_trajectory_legend_sits_beside_the_maze(tmp_path, monkeypatch):
    cfg = preset("fast", "point_medium", "mb_dscpp")
    L, N = 5, 2
    res = SimpleNamespace(xy=np.zeros((L + 1, N, 2)), option=np.ones((L, N), int),
                          active=np.ones((L, N), bool), success=np.array([True, False]),
                          upright=np.ones(N))
    seen = {}

    def keep(fig, path, rect=None):
        fig.canvas.draw()
        ax = fig.axes[0]
        seen["legend"] = ax.get_legend().get_window_extent()
        seen["axes"] = ax.get_window_extent()
    monkeypatch.setattr(plots, "_save", keep)
    plots.plot_trajectory(cfg, res, str(tmp_path / "t.png"))
    assert seen["legend"].x0 >= seen["axes"].x1            # right of the maze, not on it


# ------------------------------------------------------------------------------------------------
# Weights & Biases
# ------------------------------------------------------------------------------------------------
def test_wandb_missing_names_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "wandb", None)       # `import wandb` raises ImportError
    assert main(_train_args(str(tmp_path / "w")) + ["--wandb"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "dscpp_jax[wandb]" in line
    assert not os.path.exists(tmp_path / "w")              # refused before anything was made


def test_wandb_offline_logs_the_same_metrics_and_resumes_the_same_run(trained, tmp_path,
                                                                      monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "wb"))
    monkeypatch.setenv("WANDB_SILENT", "true")
    os.makedirs(tmp_path / "wb")
    run = _copy(trained, tmp_path)
    assert main(["train", "--resume", run, "--total-steps", "60", "--no-progress", "--wandb"]) == 0
    run_id = json.load(open(os.path.join(run, "wandb_run.json")))["id"]
    assert main(["train", "--resume", run, "--total-steps", "80", "--no-progress", "--wandb"]) == 0
    assert json.load(open(os.path.join(run, "wandb_run.json")))["id"] == run_id
    wb = tmp_path / "wb" / "wandb"
    offline = sorted(d for d in os.listdir(wb) if d.startswith("offline-run-"))
    # one wandb run resumed: both directories carry its id (wandb adds "-1" to the second when
    # both calls start within the same second)
    assert len(offline) == 2 and all(
        re.fullmatch(rf"offline-run-\d{{8}}_\d{{6}}-{re.escape(run_id)}(-\d+)?", d) for d in offline)
    data = b"".join(open(os.path.join(wb, d, f), "rb").read() for d in offline
                    for f in os.listdir(wb / d) if f.endswith(".wandb"))
    columns = [c for c in read_metrics(run) if c != "iteration"]
    for name in columns:
        if any(v == v for v in read_metrics(run)[name]):          # logged at least once
            assert name.encode() in data, name
    assert b"td3_batch_size" in data                               # the config too

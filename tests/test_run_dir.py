"""Run directories you can trust, tried through the command line as a user would (`python -m
dscpp_jax.cli train ...` in a subprocess, on tiny point-mass runs): one process per directory,
no silent overwrite, every `--resume` flag applied or refused with its reason, a `--time-budget`
the process keeps (checkpoint and stop, no final evaluation), the one-line message last on a full
disk or a damaged checkpoint (no traceback flood, no hang), a seed group too large for memory
refused before anything is written, and run files that honour the umask.

The subprocesses share one compilation cache, so a resume loads the programs its run compiled.
"""
import asyncio
import csv
import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
import types

import pytest

from dscpp_jax import config as C
from dscpp_jax import run_dir
from dscpp_jax.run_logging import RunDirError, atomic_write, os_error_fix

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# the flat TD3+HER learner on the point-mass U-maze: 2 envs x 10 steps = 20 env steps an iteration
TINY = ["num_envs=2", "steps_per_iter=10", "episode_length=40", "warmup_episodes=1",
        "buffer_len=10", "option_timeout=20", "td3_hidden=16", "td3_batch_size=16",
        "td3_updates_per_step=0.1", "replay_capacity=400", "model_capacity=400",
        "eval_episodes=2"]
STEPS_PER_ITERATION = 20
BUDGET_S = 12.0        # --time-budget of the budget tests (past the start-up: iterations to stop)
BUDGET_MARGIN_S = 25.0  # the final save and the process's exit on a loaded 2-core machine
TIMEOUT_S = 300        # a command still running after this has hung


def _sets(extra=()):
    out = []
    for s in TINY + list(extra):
        out += ["--set", s]
    return out


def _fresh(run, total, extra=()):
    """`train` arguments of a fresh tiny run in `run`."""
    return (["train", "--env", "point_u_maze", "--algo", "td3_her", "--run-dir", str(run),
             "--total-steps", str(total), "--eval-every", "0", "--no-progress"]
            + list(extra) + _sets())


@pytest.fixture(scope="module")
def xla_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("xla_cache"))


def _cli(args, cache, wrapper=None, cwd=None):
    """Run the command line in a new process (through `wrapper`'s file, which calls
    `dscpp_jax.cli.main`, where given); (return code, stdout, stderr, seconds). A command that
    does not end within TIMEOUT_S fails the test as hung."""
    cmd = [sys.executable] + ([str(wrapper)] if wrapper else ["-m", "dscpp_jax.cli"])
    env = dict(os.environ, PYTHONPATH=ROOT, DSCPP_JAX_COMPILE_CACHE=cache)
    t0 = time.monotonic()
    try:
        out = subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True,
                             env=env, cwd=cwd or ROOT, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"hung: {' '.join(args)} still running after {TIMEOUT_S}s; stderr ends "
                    f"{(e.stderr or b'')[-2000:]!r}")
    return out.returncode, out.stdout, out.stderr, time.monotonic() - t0


def _last_line(err):
    lines = [l for l in err.splitlines() if l.strip()]
    return lines[-1] if lines else ""


def _assert_one_line_error_last(err, *says):
    """The last non-empty line of stderr is the command's one-line error saying `says`, with no
    traceback anywhere in stderr."""
    last = _last_line(err)
    assert last.startswith("error: "), err[-3000:]
    for s in says:
        assert s in last, last
    assert "Traceback" not in err and "Event loop is closed" not in err, err[-3000:]
    assert len([l for l in err.splitlines() if l.strip()]) <= 6, err[-3000:]


def _rows(run):
    with open(os.path.join(run, "metrics.csv"), newline="") as f:
        return list(csv.DictReader(f))


def _steps(run):
    d = os.path.join(run, "checkpoints")
    return sorted(int(n) for n in os.listdir(d) if n.isdigit()) if os.path.isdir(d) else []


def _config(run, name="config.json"):
    with open(os.path.join(run, name)) as f:
        return C.flat_config(json.load(f)["config"])


def _startup(run):
    with open(os.path.join(run, "startup.jsonl")) as f:
        return [json.loads(l) for l in f if l.strip()]


def _listing(run):
    """Every file under `run` with its size and modification time (to show nothing changed)."""
    out = {}
    for root, _, files in os.walk(run):
        for f in files:
            st = os.stat(os.path.join(root, f))
            out[os.path.relpath(os.path.join(root, f), run)] = (st.st_size, st.st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def single(tmp_path_factory, xla_cache):
    """A finished tiny run: iterations 1 and 2, checkpoints of both."""
    run = tmp_path_factory.mktemp("single") / "run"
    rc, _, err, _ = _cli(_fresh(run, 2 * STEPS_PER_ITERATION, ["--checkpoint-every", "1"]),
                         xla_cache)
    assert rc == 0, err[-3000:]
    assert _steps(run) == [1, 2] and len(_rows(run)) == 2
    return str(run)


def _copy(src, tmp_path, name="run"):
    dst = str(tmp_path / name)
    shutil.copytree(src, dst)
    return dst


def test_a_second_process_is_refused_naming_the_first(tmp_path):
    d = str(tmp_path / "run")
    os.makedirs(d)
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from dscpp_jax import run_dir
            run_dir.lock_run_dir({d!r})
            print("locked", flush=True)
            sys.stdin.readline()
        """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONPATH=ROOT))
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(run_dir.RunDirLocked, match=str(holder.pid)):
            run_dir.lock_run_dir(d)
    finally:
        holder.communicate("\n", timeout=60)
    run_dir.lock_run_dir(d)          # free again once the holder exits
    run_dir.lock_run_dir(d)          # and a second call from the holding process is a no-op
    run_dir.unlock_run_dir(d)


def test_an_existing_run_is_refused_unless_overwritten(tmp_path):
    d = tmp_path / "run"
    (d / "checkpoints" / "4").mkdir(parents=True)
    (d / "config.json").write_text("{}")
    (d / "metrics.csv").write_text("iteration\n1\n")
    (d / "eval.json").write_text("{}")
    (d / "notes.txt").write_text("mine")
    run_dir.check_fresh(str(tmp_path / "empty"))     # a new directory is fine
    with pytest.raises(RunDirError, match="--resume|--overwrite"):
        run_dir.check_fresh(str(d))
    assert (d / "config.json").exists() and (d / "checkpoints").exists()
    run_dir.check_fresh(str(d), overwrite=True)
    assert not run_dir.existing_run(str(d))
    assert not (d / "checkpoints").exists() and not (d / "eval.json").exists()
    assert (d / "notes.txt").read_text() == "mine"    # what train does not write stays


def test_run_files_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        p = tmp_path / "config.json"
        atomic_write(str(p), "{}")
        assert (p.stat().st_mode & 0o777) == 0o644
        os.umask(0o077)
        atomic_write(str(p), "{}")
        assert (p.stat().st_mode & 0o777) == 0o600
    finally:
        os.umask(old)


def test_train_refuses_an_existing_run(tmp_path, capsys):
    """Through the command line (`main`, as `python -m dscpp_jax.cli` calls it): refused before
    anything is compiled or written."""
    from dscpp_jax.cli import main
    d = tmp_path / "run"
    d.mkdir()
    (d / "config.json").write_text("{}")
    assert main(["train", "--env", "point_u_maze", "--run-dir", str(d), "--no-progress"]) == 2
    _assert_one_line_error_last(capsys.readouterr().err, "already holds a run", "--resume",
                                "--overwrite")
    assert (d / "config.json").read_text() == "{}"


# ------------------------------------------------------------------------------------------------
# --resume: every flag applied or refused with the reason
# ------------------------------------------------------------------------------------------------
REFUSED_ON_RESUME = [   # (flags, what the error says) for the run of `single`
    (["--num-envs", "4"], ["--num-envs 4", "num_envs=2"]),
    (["--steps-per-iter", "20"], ["--steps-per-iter 20", "steps_per_iter=10"]),
    (["--env", "point_medium"], ["--env point_medium", "env=point_u_maze"]),
    (["--algo", "mb_dscpp"], ["--algo mb_dscpp", "algo=td3_her"]),
    (["--seed", "3"], ["--seed 3", "seed=0"]),
    (["--subgoal", "dp"], ["--subgoal dp", "subgoal=robust"]),
    (["--physics", "warp"], ["--physics warp", "physics=jax"]),
    (["--set", "td3_hidden=32"], ["td3_hidden=32", "td3_hidden=16"]),
    (["--preset", "paper"], ["--preset paper"]),
    (["--overwrite"], ["--overwrite"]),
    (["--run-dir", "elsewhere"], ["--run-dir elsewhere"]),
    (["--num-envs", "4", "--seed", "3"], ["--num-envs 4", "--seed 3"]),   # each is named
]
REFUSED_ON_GROUP_RESUME = [   # for the group of `budget_group`
    (["--seed", "1"], ["--seed 1", "its own seeds"]),
    (["--seeds", "0-1"], ["--seeds"]),
    (["--num-envs", "4"], ["--num-envs 4", "num_envs=2"]),
    (["--preset", "paper"], ["--preset paper"]),
]


def _refused(run, table, capsys):
    from dscpp_jax.cli import main
    before = _listing(run)
    for flags, says in table:
        assert main(["train", "--resume", run, "--no-progress"] + flags) == 2, flags
        err = capsys.readouterr().err
        _assert_one_line_error_last(err, "--resume cannot change" if flags[0] != "--seeds"
                                    else "--resume", *says)
    assert _listing(run) == before   # nothing written


def test_resume_refuses_what_the_checkpoint_fixes_naming_each_flag(single, tmp_path, capsys):
    """Refused before anything is compiled or written; the flags in one process (`main`), as
    `python -m dscpp_jax.cli` calls it."""
    _refused(_copy(single, tmp_path), REFUSED_ON_RESUME, capsys)


# ------------------------------------------------------------------------------------------------
# --time-budget: counted from the process's start; checkpoint and stop, no final evaluation
# ------------------------------------------------------------------------------------------------
def _assert_kept_the_budget(run, rc, err, seconds, startup_record):
    assert rc == 0, err[-3000:]
    assert "time budget" in err and "reached" in err
    # within the budget, unless the first iteration (which compiles) alone ended past it
    first = startup_record["command_to_first_iteration_s"]
    assert seconds <= max(BUDGET_S, first) + BUDGET_MARGIN_S, (seconds, first)


@pytest.fixture(scope="module")
def budget_single(tmp_path_factory, xla_cache):
    run = tmp_path_factory.mktemp("budget") / "run"
    rc, out, err, seconds = _cli(_fresh(run, 10 ** 6, ["--time-budget", BUDGET_S,
                                                       "--checkpoint-every", "1"]), xla_cache)
    return str(run), rc, out, err, seconds


def test_time_budget_of_a_single_run(budget_single):
    run, rc, out, err, seconds = budget_single
    _assert_kept_the_budget(run, rc, err, seconds, _startup(run)[0])
    k = len(_rows(run))
    assert k >= 1 and _steps(run)[-1] == k          # the checkpoint of the last iteration
    assert not os.path.exists(os.path.join(run, "eval.json"))   # no final evaluation
    assert f"--resume {run}" in out


def test_resume_applies_every_allowed_flag_and_accepts_equal_fixed_ones(budget_single, tmp_path,
                                                                         xla_cache):
    """Continues the budget-stopped run with every flag `--resume` may change, and the flags the
    checkpoint fixes at the values it has: each change shows in what the run does and in its
    config.json."""
    run = _copy(budget_single[0], tmp_path)
    k = len(_rows(run))
    before = _steps(run)
    total = (k + 3) * STEPS_PER_ITERATION
    applied = {"total_env_steps": total, "total_episodes": 1000, "eval_every": 2,
               "eval_episodes": 3, "checkpoint_every": 2, "keep_checkpoints": 3}
    rc, out, err, _ = _cli(
        ["train", "--resume", run, "--no-progress", "--total-steps", total,
         "--total-episodes", "1000", "--eval-every", "2", "--eval-episodes", "3",
         "--checkpoint-every", "2", "--set", "keep_checkpoints=3", "--set", "eval.episodes=3",
         "--env", "point_u_maze", "--algo", "td3_her", "--seed", "0", "--num-envs", "2",
         "--set", "td3_hidden=16"], xla_cache)
    assert rc == 0, err[-3000:]
    assert f"resumed {run} at iteration {k}" in err
    rows = _rows(run)
    assert [int(r["iteration"]) for r in rows] == list(range(1, k + 4))
    assert int(rows[-1]["env_steps"]) == total                      # --total-steps
    new = list(range(k + 1, k + 4))
    evaluated = [i for i in new if rows[i - 1]["eval/success_rate"] != ""]
    assert evaluated == [i for i in new if i % 2 == 0 or i == k + 3]   # --eval-every
    saved = {i for i in new if i % 2 == 0} | {k + 3}                    # --checkpoint-every
    assert _steps(run) == sorted(set(before) | saved)[-3:]              # keep_checkpoints
    assert os.path.exists(os.path.join(run, "eval.json"))   # the schedule's end: evaluated
    cfg = _config(run)
    assert {f: cfg[f] for f in applied} == applied


@pytest.fixture(scope="module")
def budget_group(tmp_path_factory, xla_cache):
    group = tmp_path_factory.mktemp("budget_group") / "group"
    rc, out, err, seconds = _cli(
        _fresh(group, 10 ** 6, ["--seeds", "0-1", "--time-budget", BUDGET_S]), xla_cache)
    return str(group), rc, out, err, seconds


def test_time_budget_of_a_seed_group_and_its_resume(budget_group, tmp_path, xla_cache, capsys):
    group, rc, out, err, seconds = budget_group
    _assert_kept_the_budget(group, rc, err, seconds, _startup(group)[0])
    assert f"--resume {group}" in out
    k = len(_rows(os.path.join(group, "s0")))
    assert k >= 1 and _steps(group)[-1] == k
    for s in (0, 1):
        assert not os.path.exists(os.path.join(group, f"s{s}", "eval.json"))
    group = _copy(group, tmp_path, "group")   # the fixture's run stays for the other tests

    _refused(_copy(group, tmp_path, "refused"), REFUSED_ON_GROUP_RESUME, capsys)

    # a later --resume continues it, with the cadences it is given, to the schedule's end
    total = (k + 1) * STEPS_PER_ITERATION
    rc, out, err, _ = _cli(["train", "--resume", group, "--no-progress", "--total-steps", total,
                            "--eval-episodes", "3", "--checkpoint-every", "1"], xla_cache)
    assert rc == 0, err[-3000:]
    assert f"at iteration {k}" in err
    for s in (0, 1):
        d = os.path.join(group, f"s{s}")
        assert [int(r["iteration"]) for r in _rows(d)] == list(range(1, k + 2))
        with open(os.path.join(d, "eval.json")) as f:
            assert json.load(f)["iteration"] == k + 1
        assert _config(d)["eval_episodes"] == 3 and _config(d)["seed"] == s
    assert _config(group, "group.json")["total_env_steps"] == total
    assert _steps(group)[-1] == k + 1


# ------------------------------------------------------------------------------------------------
# A full disk: the one-line message last, no traceback flood, no hang
# ------------------------------------------------------------------------------------------------
FULL_DISK = textwrap.dedent('''
    """Run the command line (`dscpp_jax.cli.main`) on a run directory whose disk fills up.

        python full_disk.py RUN_DIR files TRIGGER ARGS...   once a file under RUN_DIR whose path
            holds TRIGGER is opened for writing, every later write under RUN_DIR fails (ENOSPC,
            naming no file, as a write on a full disk fails)
        python full_disk.py RUN_DIR orbax ARGS...   orbax's writing of a checkpoint's files fails
            as tensorstore reports a full disk (a ValueError, RESOURCE_EXHAUSTED)
    """
    import builtins, errno, io, os, sys

    run_dir, mode = os.path.abspath(sys.argv[1]), sys.argv[2]
    trigger = sys.argv[3] if mode == "files" else None
    argv = sys.argv[4:] if mode == "files" else sys.argv[3:]
    full = [False]
    real_open, real_os_open = builtins.open, os.open

    def check(path, writing):
        if not writing or not isinstance(path, (str, bytes, os.PathLike)):
            return
        p = os.path.abspath(os.fsdecode(path))
        if p.startswith(run_dir + os.sep):
            full[0] = full[0] or trigger in p
            if full[0]:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def full_open(file, mode="r", *a, **k):
        check(file, any(c in mode for c in "wax+"))
        return real_open(file, mode, *a, **k)

    def full_os_open(path, flags, *a, **k):
        check(path, bool(flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)))
        return real_os_open(path, flags, *a, **k)

    if mode == "files":
        builtins.open = io.open = full_open
        os.open = full_os_open
    else:
        import orbax.checkpoint as ocp

        def full_finalize(self, step, *a, **k):
            path = os.path.join(run_dir, "checkpoints", f"{step}.orbax-checkpoint-tmp", "d")
            raise ValueError(f"RESOURCE_EXHAUSTED: Error writing local file \\"{path}\\": "
                             f"No space left on device [os_error_code=28]")
        assert hasattr(ocp.CheckpointManager, "_finalize"), "orbax changed: update this test"
        ocp.CheckpointManager._finalize = full_finalize
    sys.argv = ["dscpp_jax.cli"] + argv
    from dscpp_jax import cli
    sys.exit(cli.main())
''')


@pytest.mark.parametrize("where", ["metrics", "checkpoint"])
def test_full_disk_ends_in_one_line(single, tmp_path, xla_cache, where):
    """metrics.csv: its append fails at the first iteration after the resume. A checkpoint:
    its background write fails in orbax's finalize thread, as tensorstore fails on a full disk
    (this hung: the error chain orbax builds loops)."""
    run = _copy(single, tmp_path)
    wrapper = tmp_path / "full_disk.py"
    wrapper.write_text(FULL_DISK)
    how = ["files", "metrics.csv"] if where == "metrics" else ["orbax"]
    rc, out, err, _ = _cli([run] + how + ["train", "--resume", run, "--total-steps", "200",
                                          "--checkpoint-every", "1", "--no-progress"],
                           xla_cache, wrapper=wrapper)
    assert rc == 2, err[-3000:]
    _assert_one_line_error_last(err, "is full", f"--resume {run}",
                                "metrics.csv" if where == "metrics" else "checkpoint")
    assert _steps(run)[:2] == [1, 2]   # what was saved stays (the simulated failure comes
    # after orbax committed the step's files, so that step may be there too)


def test_full_disk_at_a_seed_groups_checkpoint_ends_in_one_line(budget_group, tmp_path,
                                                                 xla_cache):
    group = _copy(budget_group[0], tmp_path, "group")
    before = _steps(group)
    wrapper = tmp_path / "full_disk.py"
    wrapper.write_text(FULL_DISK)
    rc, out, err, _ = _cli([group, "orbax", "train", "--resume", group, "--total-steps", 10 ** 6,
                            "--checkpoint-every", "1", "--no-progress"], xla_cache,
                           wrapper=wrapper)
    assert rc == 2, err[-3000:]
    assert _steps(group)[:len(before)] == before   # (as for a single run)
    _assert_one_line_error_last(err, "is full", f"--resume {group}", "checkpoint")


@pytest.mark.parametrize("name", ["eval.json", "group.json"])
def test_full_disk_at_a_seed_groups_files_ends_in_one_line(budget_group, tmp_path, xla_cache,
                                                           name):
    """A resume to the schedule's end writes each seed's eval.json, then the group's updated
    group.json: a full disk there ends in one line that names the file."""
    group = _copy(budget_group[0], tmp_path, "group")
    k = len(_rows(os.path.join(group, "s0")))
    wrapper = tmp_path / "full_disk.py"
    wrapper.write_text(FULL_DISK)
    rc, out, err, _ = _cli([group, "files", name, "train", "--resume", group, "--total-steps",
                            (k + 1) * STEPS_PER_ITERATION, "--no-progress"], xla_cache,
                           wrapper=wrapper)
    assert rc == 2, err[-3000:]
    _assert_one_line_error_last(err, "is full", name)
    with open(os.path.join(group, "group.json")) as f:
        json.load(f)   # a failed update leaves the group's file whole


def test_a_failed_saves_closed_loop_reports_are_dropped():
    """The hook `checkpoint.quiet_orbax` installs drops asyncio's "Event loop is closed" from
    call_soon_threadsafe (tensorstore finishing the writes of a failed save, one traceback per
    array) and hands every other report to the hook before it."""
    from dscpp_jax import checkpoint as ck
    loop = asyncio.new_event_loop()
    loop.close()
    try:
        loop.call_soon_threadsafe(print)
    except RuntimeError as e:
        closed = e
    seen = []
    old = sys.unraisablehook
    try:
        sys.unraisablehook = seen.append
        ck.quiet_orbax()
        report = types.SimpleNamespace(exc_type=RuntimeError, exc_value=closed, object=None,
                                       exc_traceback=closed.__traceback__.tb_next, err_msg=None)
        sys.unraisablehook(report)
        other = types.SimpleNamespace(exc_type=RuntimeError, exc_value=RuntimeError("other"),
                                      exc_traceback=None, object=None, err_msg=None)
        sys.unraisablehook(other)
    finally:
        sys.unraisablehook = old
    assert seen == [other]


def test_the_fix_of_an_error_whose_chain_loops_is_found():
    """`os_error_fix` follows causes and contexts to the OSError; a chain that loops (orbax
    raises a failed save's error again while the error made from it is handled) ends."""
    inner = ValueError("RESOURCE_EXHAUSTED: No space left on device [os_error_code=28]")
    outer = RuntimeError(f"could not save the checkpoint ({inner})")
    outer.__cause__ = inner
    inner.__context__ = outer
    assert "is full" in os_error_fix(outer, "/run")
    looped = ValueError("something else")
    looped.__context__ = looped
    assert "check the disk" in os_error_fix(looped, "/run")
    disk = OSError(errno.ENOSPC, "No space")
    wrapped = ValueError("write failed")
    wrapped.__context__, disk.__context__ = disk, wrapped
    assert "is full" in os_error_fix(wrapped, "/run")


# ------------------------------------------------------------------------------------------------
# A damaged newest checkpoint
# ------------------------------------------------------------------------------------------------
def _damage(run, step):
    """Cut the newest checkpoint's array metadata in half (a write cut short)."""
    path = os.path.join(run, "checkpoints", str(step), "default", "_METADATA")
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def test_a_damaged_newest_checkpoint(single, tmp_path, xla_cache):
    """Today's behaviour: `--resume` falls back to the newest checkpoint that restores, says so in
    one warning line naming both iterations, moves the damaged one aside (nothing is deleted)
    and trains its iterations again. With none that restores: a one-line error, last."""
    run = _copy(single, tmp_path)
    _damage(run, 2)
    rc, out, err, _ = _cli(["train", "--resume", run, "--total-steps", "60", "--no-progress"],
                           xla_cache)
    assert rc == 0, err[-3000:]
    warnings = [l for l in err.splitlines() if l.startswith("WARNING")]
    assert len(warnings) == 1 and "iteration 2" in warnings[0], err[-3000:]
    assert "Using iteration 1" in warnings[0]
    assert "Traceback" not in err and len([l for l in err.splitlines() if l.strip()]) <= 5, err
    assert _steps(run) == [2, 3]
    assert os.listdir(os.path.join(run, "checkpoints_unrestorable"))[0].startswith("2-")
    assert [int(r["iteration"]) for r in _rows(run)] == [1, 2, 3]

    for s in _steps(run):
        _damage(run, s)
    before = _listing(run)
    rc, out, err, _ = _cli(["train", "--resume", run, "--total-steps", "80", "--no-progress"],
                           xla_cache)
    assert rc == 2
    _assert_one_line_error_last(err, "no checkpoint under", "iteration 2", "iteration 3")
    def kept(listing):   # all but the lock (it records the PID) and the logs a start appends to
        return {k: v for k, v in listing.items()
                if k not in (".lock", "startup.jsonl") and not k.startswith("tb")}
    assert kept(_listing(run)) == kept(before)


# ------------------------------------------------------------------------------------------------
# A seed group too large for memory
# ------------------------------------------------------------------------------------------------
def test_a_seed_group_too_large_for_memory_is_refused_before_anything_is_written(tmp_path,
                                                                                  monkeypatch,
                                                                                  capsys):
    """Through the command line (`main`, as `python -m dscpp_jax.cli` calls it): the refusal
    comes before anything is compiled, so a process of its own would only add its start-up."""
    from dscpp_jax.cli import main
    monkeypatch.chdir(tmp_path)   # where the default runs/ directory would go
    # capacities large enough that no host holds 5001 seeds (about 1 TiB)
    assert main(["train", "--env", "point_u_maze", "--seeds", "0-5000", "--no-progress",
                 "--set", "replay_capacity=2000000", "--set", "model_capacity=2000000"]) == 2
    _assert_one_line_error_last(capsys.readouterr().err, "5001 seeds does not fit", "at most",
                                "Nothing was written")
    assert os.listdir(tmp_path) == []   # no runs/ directory, no seed directories

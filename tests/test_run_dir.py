"""Run directories one process owns: the lock, the refusal to write over an existing run, the
clearing `--overwrite` asks for, and run files that honour the umask (fast, no training)."""
import os
import subprocess
import sys
import textwrap

import pytest

from dscpp_jax import run_dir
from dscpp_jax.run_logging import RunDirError, atomic_write

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


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


def test_train_refuses_an_existing_run_and_resume_refuses_a_changed_env(tmp_path):
    """Through the command line: both are refused before anything is compiled or written."""
    from dscpp_jax.cli import build_parser, resume_changes
    from dscpp_jax.config import preset
    d = tmp_path / "run"
    d.mkdir()
    (d / "config.json").write_text("{}")
    out = subprocess.run([sys.executable, "-m", "dscpp_jax.cli", "train", "--env", "point_u_maze",
                          "--run-dir", str(d), "--no-progress"], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=ROOT), timeout=300)
    assert out.returncode != 0
    assert "already holds a run" in out.stderr + out.stdout
    assert (d / "config.json").read_text() == "{}"

    saved = preset("fast", env="point_u_maze", algo="mb_dscpp")
    p = build_parser()
    same = p.parse_args(["train", "--resume", str(d), "--env", "point_u_maze",
                         "--total-episodes", "50"])
    assert resume_changes(same, saved)["total_episodes"] == 50   # applied
    changed = p.parse_args(["train", "--resume", str(d), "--env", "point_medium"])
    with pytest.raises(ValueError, match="point_medium"):
        resume_changes(changed, saved)

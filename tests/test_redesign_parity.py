"""Behaviour pinned across refactors: fixed commands on the CPU give the metrics.csv files that
the code of commit 03050be wrote, cell for cell, and a run directory that code checkpointed
resumes to the rows its uninterrupted run wrote.

The golden files live in tests/data/parity and come from experiments/make_parity_fixtures.py
run on that commit (tests/data/parity/SOURCE.json records the commands). Everything goes
through the command line and the files of a run directory, the interface that stays:

- single: MB-DSC++ on the point-mass U-maze, one seed, N_ITERS iterations;
- group: MF-DSC++, seeds 0-1 as one seed group, N_ITERS iterations;
- old checkpoint: the single run's command stopped after K_ITERS iterations, a whole run
  directory with its checkpoint, resumed here to N_ITERS.

The settings are small but reach the skill chain: warm-up ends, the goal option matures and a
new option starts its gestation, with in-band evaluations every other iteration.

Cells are compared as text, exactly: CPU runs repeat bit for bit on one machine (two
generations of the fixtures give identical files apart from the wall-clock columns in
WALL_CLOCK_COLUMNS). The one exception is a logged loss (a column ending in "loss"): it is a mean
over a minibatch that XLA's CPU code sums in an order that depends on the processor's vector
width, so on another machine its last printed digit can differ; those cells must agree to a
relative LOSS_RTOL. Nothing feeds a logged loss back into training, so any change of behaviour
still shows in the exact columns. The
subprocesses get fixed XLA_FLAGS (FIXTURE_XLA_FLAGS, the test runner's quick compile flags), so
that the compiled programs do not depend on the caller's environment.
"""
import csv
import os
import shutil
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA = os.path.join(ROOT, "tests", "data", "parity")

N_ITERS = 8          # iterations of the single run and of the group
K_ITERS = 4          # iterations before the old checkpoint (a multiple of the eval cadence)
NUM_ENVS = 16
STEPS_PER_ITER = 20
STEPS = NUM_ENVS * STEPS_PER_ITER   # env steps per iteration, all envs together
SETS = [f"num_envs={NUM_ENVS}", f"steps_per_iter={STEPS_PER_ITER}", "episode_length=40",
        "warmup_episodes=2", "goal_tolerance=3.0", "max_options=4", "max_pos_traj=8",
        "max_neg=8", "buffer_len=10", "option_timeout=20", "gestation=1", "td3_hidden=32",
        "td3_batch_size=32", "td3_updates_per_step=0.1", "replay_capacity=2000",
        "model_capacity=2000", "dyn_hidden=16", "dyn_batch_size=32", "dyn_updates_per_step=0.05",
        "dyn_pretrain_steps=5", "mpc_samples=32", "mpc_horizon=3", "eval_episodes=2",
        "frontier_candidates=64"]
COMMON = ["--env", "point_u_maze", "--eval-every", "2", "--checkpoint-every", str(K_ITERS),
          "--no-progress"] + [a for s in SETS for a in ("--set", s)]
FIXTURE_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
# Columns that measure time on the host, not behaviour (the only columns that differ between two
# generations of the fixtures); every other column is compared. The last is a seed group's.
WALL_CLOCK_COLUMNS = ("wall_clock", "time/iteration_s", "time/env_steps_per_s",
                      "time/group_env_steps_per_s")
TIMEOUT_S = 900
LOSS_RTOL = 1e-5     # logged losses: the sixth significant digit may differ across processors


def single_args(run_dir: str, iterations: int = N_ITERS) -> list:
    """`train` of the single run (MB-DSC++, seed 0) for `iterations` iterations."""
    return ["train", "--algo", "mb_dscpp", "--seed", "0", "--run-dir", run_dir,
            "--total-steps", str(iterations * STEPS)] + COMMON


def group_args(group_dir: str) -> list:
    """`train` of the two-seed group (MF-DSC++, seeds 0-1)."""
    return ["train", "--algo", "mf_dscpp", "--seeds", "0-1", "--run-dir", group_dir,
            "--total-steps", str(N_ITERS * STEPS)] + COMMON


def resume_args(run_dir: str) -> list:
    """`train --resume` of the old checkpoint up to N_ITERS iterations."""
    return ["train", "--resume", run_dir, "--total-steps", str(N_ITERS * STEPS), "--no-progress"]


def cli_env() -> dict:
    """The environment of every command: CPU, fixed XLA flags, this checkout on the path."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("XLA_FLAGS", "DSCPP_JAX_COMPILE_CACHE", "JAX_ENABLE_X64")}
    env.update(JAX_PLATFORMS="cpu", XLA_FLAGS=FIXTURE_XLA_FLAGS, PYTHONPATH=ROOT,
               TF_CPP_MIN_LOG_LEVEL="3")
    return env


def start_cli(args: list, log_path: str, compile_cache: str = "off") -> subprocess.Popen:
    """Start `python -m dscpp_jax.cli ARGS --compile-cache DIR`, its output in `log_path`."""
    log = open(log_path, "w")
    proc = subprocess.Popen([sys.executable, "-m", "dscpp_jax.cli", *args,
                             "--compile-cache", compile_cache],
                            cwd=ROOT, env=cli_env(), stdout=log, stderr=subprocess.STDOUT)
    proc.log_file = log
    return proc


def finish_cli(proc: subprocess.Popen, what: str) -> None:
    """Wait for a command started by `start_cli`; fail with its output when it fails."""
    try:
        rc = proc.wait(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        rc = "timeout"
    proc.log_file.close()
    if rc != 0:
        with open(proc.log_file.name) as f:
            out = f.read()
        raise AssertionError(f"{what} failed ({rc}):\n{out[-4000:]}")


def read_rows(path: str) -> list:
    """metrics.csv as a list of {column: text} rows, wall-clock columns left out."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return [{k: v for k, v in r.items() if k not in WALL_CLOCK_COLUMNS} for r in rows]


def same_loss(column: str, got: str, want: str) -> bool:
    """Whether `column` is a logged loss and its two cells agree to LOSS_RTOL."""
    if not column.endswith("loss"):
        return False
    try:
        g, w = float(got), float(want)
    except ValueError:
        return False
    return abs(g - w) <= LOSS_RTOL * max(abs(w), 1e-12)


def assert_rows_equal(got: list, want: list, what: str) -> None:
    """Equal row for row and cell for cell, naming the first cell that differs."""
    assert len(got) == len(want), f"{what}: {len(got)} rows, expected {len(want)}"
    for i, (g, w) in enumerate(zip(got, want)):
        assert set(g) == set(w), (f"{what}, row {i + 1}: columns differ: extra "
                                  f"{sorted(set(g) - set(w))}, missing {sorted(set(w) - set(g))}")
        bad = [(k, g[k], w[k]) for k in sorted(w)
               if g[k] != w[k] and not same_loss(k, g[k], w[k])]
        assert not bad, (f"{what}, row {i + 1} (iteration {w.get('iteration')}): "
                         f"{len(bad)} cells differ, first (column, got, expected): {bad[:5]}")


def test_single_run_group_and_old_checkpoint_match_the_pinned_files(tmp_path):
    cache = str(tmp_path / "xla_cache")   # the resume below loads the single run's programs
    single = str(tmp_path / "single")
    group = str(tmp_path / "group")
    old = str(tmp_path / "old_checkpoint")
    shutil.copytree(os.path.join(DATA, "old_checkpoint"), old)

    procs = [(start_cli(single_args(single), str(tmp_path / "single.log"), cache), "single run"),
             (start_cli(group_args(group), str(tmp_path / "group.log"), cache), "seed group")]
    for proc, what in procs:
        finish_cli(proc, what)
    golden = read_rows(os.path.join(DATA, "single", "metrics.csv"))
    assert len(golden) == N_ITERS
    assert_rows_equal(read_rows(os.path.join(single, "metrics.csv")), golden, "single run")
    for s in (0, 1):
        want = read_rows(os.path.join(DATA, "group", f"s{s}", "metrics.csv"))
        assert len(want) == N_ITERS
        assert_rows_equal(read_rows(os.path.join(group, f"s{s}", "metrics.csv")), want,
                          f"seed group, seed {s}")

    # the old run directory: rows 1..K as it wrote them, then K+1..N from its checkpoint
    assert_rows_equal(read_rows(os.path.join(old, "metrics.csv")), golden[:K_ITERS],
                      "old checkpoint before resuming")
    proc = start_cli(resume_args(old), str(tmp_path / "resume.log"), cache)
    finish_cli(proc, "resume of the old checkpoint")
    assert_rows_equal(read_rows(os.path.join(old, "metrics.csv")), golden,
                      "resumed old checkpoint")

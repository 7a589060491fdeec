"""Run every tests/test_*.py in its own pytest process, a few at a time; the suite's entry point.

One process per file: late in a single ~160-test process, XLA's CPU compiler has crashed (SIGSEGV
while compiling a function that compiles fine in a fresh process). Compiling is most of the
suite's time and XLA's compiler is mostly one thread, so two files at a time on two cores take
about half the wall-clock of one after another. The longest files start first (the order below,
from the suite's own timings); each file's output is printed whole when it ends.

Every file compiles with XLA's older CPU fusion code generator (`--xla_cpu_use_fusion_emitters=
false`, where this XLA still has the switch), which compiles in less time than its MLIR fusion
emitters; the pinned runs of tests/test_redesign_parity.py come out the same, and the kernel
comparisons of test_learning.py and test_svm.py hold with it. Except test_bench_replay_draws.py:
it checks that two programs (two ways of drawing the model's minibatches) train bitwise the same
model, which they do with the MLIR emitters, but not with the older generator at the lowest
optimisation level.

Files compile without XLA's expensive LLVM passes (about a fifth less in all), except
test_learning.py (its learning runs execute more than they compile, about a third less CPU time
at full optimisation, and it compares the interpreted SMO and MPC kernels inside train_step with
XLA's path at 1e-5) and test_svm.py (it compares the interpreted SMO kernel with XLA's loop, which
at the lowest optimisation level round apart on jax 0.10.2). Every other trainer test is in
test_trainer.py, at the fast flags (about 40 % less CPU time than at full optimisation).

The files share one JAX persistent compilation cache, a fresh temporary directory removed at the
end: many files (and the command-line processes they start) compile the same programs for the
same small configs, and a program loaded from the cache is the compiled one, so it computes the
same numbers. `--compile-cache off` compiles everything in every process.

    python tests/run_files.py [--jobs N] [--compile-cache off] [FILES...]
"""
from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed

FAST_XLA = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
LEGACY_FUSION = "--xla_cpu_use_fusion_emitters=false"
FULL_XLA = {"test_learning.py", "test_svm.py"}
MLIR_FUSION = {"test_bench_replay_draws.py"}   # compiled without LEGACY_FUSION
# Longest first (CPU time), every file, so that the last files to start are short ones (seconds
# on the 2-core CI machine) and the two workers finish together; a file not listed starts last.
LONGEST_FIRST = ["test_learning.py", "test_reproduce.py", "test_run_dir.py", "test_trainer.py",
                 "test_seed_group.py", "test_inband.py", "test_envs_ant.py", "test_td3.py",
                 "test_redesign_parity.py", "test_option_critics.py", "test_cli.py",
                 "test_svm.py", "test_mpc.py", "test_frontier_goal.py", "test_prewarm.py",
                 "test_profile_train_step.py", "test_frontier.py", "test_checkpoint.py",
                 "test_option_learners.py", "test_dynamics.py", "test_options.py",
                 "test_replay_her.py", "test_errors.py", "test_initiation.py",
                 "test_envs_layout.py", "test_subgoals.py", "test_video.py",
                 "test_time_to_threshold.py", "test_compare.py", "test_bench_replay_draws.py",
                 "test_warp_kernels.py", "test_startup_clock.py", "test_config.py",
                 "test_diagnose.py", "test_runtime.py", "test_probe_matmul_precision.py",
                 "test_repo_layout.py"]


def _order(files: list[pathlib.Path]) -> list[pathlib.Path]:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    return sorted(files, key=lambda f: (rank.get(f.name, len(rank)), f.name))


def _legacy_fusion() -> str:
    """LEGACY_FUSION where this XLA knows the flag, else "" (XLA aborts on a flag it does not
    know, so a newer XLA that dropped it would fail every file)."""
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"],
                           env=dict(os.environ, XLA_FLAGS=LEGACY_FUSION, JAX_PLATFORMS="cpu"),
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return LEGACY_FUSION if probe.returncode == 0 else ""


def _cache_env(path: str) -> dict:
    """JAX's settings for a persistent compilation cache in `path` that keeps every program."""
    return {"JAX_COMPILATION_CACHE_DIR": path, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
            "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "-1"}


def _run(path: pathlib.Path, cache: str | None, legacy: str
         ) -> tuple[pathlib.Path, int, float, float, str]:
    env = dict(os.environ, **(_cache_env(cache) if cache else {}))
    legacy = "" if path.name in MLIR_FUSION else legacy
    flags = legacy if path.name in FULL_XLA else f"{FAST_XLA} {legacy}".strip()
    if flags:
        env["XLA_FLAGS"] = f"{env['XLA_FLAGS']} {flags}" if env.get("XLA_FLAGS") else flags
    start = time.monotonic()
    with tempfile.TemporaryFile("w+") as log:
        proc = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                 str(path)], stdout=log, stderr=subprocess.STDOUT, env=env)
        _, status, usage = os.wait4(proc.pid, 0)   # the file's CPU time, its subprocesses included
        proc.returncode = os.waitstatus_to_exitcode(status)
        log.seek(0)
        return (path, proc.returncode, time.monotonic() - start, usage.ru_utime + usage.ru_stime,
                log.read())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="test files at a time (default: 2, or 1 on a one-core machine)")
    ap.add_argument("--compile-cache", choices=["on", "off"], default="on",
                    help="share one compilation cache between the files (default: on)")
    ap.add_argument("files", nargs="*", help="test files (default: tests/test_*.py)")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error("--jobs must be at least 1")
    root = pathlib.Path(__file__).resolve().parent
    files = [pathlib.Path(f) for f in args.files] or sorted(root.glob("test_*.py"))
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        ap.error(f"no such test file: {', '.join(missing)}")
    start = time.monotonic()
    failed = []
    cpu_total = 0.0
    cache = tempfile.mkdtemp(prefix="dscpp_jax_tests_xla_") if args.compile_cache == "on" else None
    legacy = _legacy_fusion()
    try:
        with ThreadPoolExecutor(args.jobs) as pool:
            # started in this order
            futures = [pool.submit(_run, f, cache, legacy) for f in _order(files)]
            for future in as_completed(futures):
                path, rc, secs, cpu, out = future.result()
                cpu_total += cpu
                print(f"== {path.name} ({secs:.0f} s, {cpu:.0f} CPU-s, "
                      f"{'passed' if rc == 0 else 'FAILED'})")
                print(out, end="", flush=True)
                if rc != 0:
                    failed.append(path.name)
    finally:
        if cache:
            shutil.rmtree(cache, ignore_errors=True)
    total = time.monotonic() - start
    if failed:
        print(f"some test files FAILED ({', '.join(failed)}); {total:.0f} s, {cpu_total:.0f} CPU-s")
        return 1
    print(f"all test files passed; {total:.0f} s ({cpu_total:.0f} CPU-s) with {args.jobs} at a time")
    return 0


if __name__ == "__main__":
    sys.exit(main())

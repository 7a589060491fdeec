"""Run every tests/test_*.py in its own pytest process, a few at a time; the suite's entry point.

One process per file: late in a single ~160-test process, XLA's CPU compiler has crashed (SIGSEGV
while compiling a function that compiles fine in a fresh process). Compiling is most of the
suite's time and XLA's compiler is mostly one thread, so two files at a time on two cores take
about half the wall-clock of one after another. The longest files start first (the order below,
from the suite's own timings); each file's output is printed whole when it ends.

Files compile without XLA's expensive LLVM passes (about a fifth less in all), except
test_trainer.py (its learning runs execute more than they compile, and it compares the
interpreted MPC kernel with XLA's path at 1e-5) and test_svm.py (it compares the interpreted SMO
kernel with XLA's loop, which at the lowest optimisation level round apart on jax 0.10.2).

    python tests/run_files.py [--jobs N] [FILES...]
"""
from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed

FAST_XLA = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
FULL_XLA = {"test_trainer.py", "test_svm.py"}
# Longest first, so that the last file to start is a short one (seconds on the 2-core CI machine).
LONGEST_FIRST = ["test_trainer.py", "test_option_learners.py", "test_inband.py",
                 "test_seed_group.py", "test_run_dir.py", "test_reproduce.py", "test_envs_ant.py",
                 "test_td3.py", "test_option_critics.py", "test_redesign_parity.py",
                 "test_profile_train_step.py", "test_options.py", "test_mpc.py"]


def _order(files: list[pathlib.Path]) -> list[pathlib.Path]:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    return sorted(files, key=lambda f: (rank.get(f.name, len(rank)), f.name))


def _run(path: pathlib.Path) -> tuple[pathlib.Path, int, float, str]:
    env = dict(os.environ)
    if path.name not in FULL_XLA:
        env["XLA_FLAGS"] = f"{env['XLA_FLAGS']} {FAST_XLA}" if env.get("XLA_FLAGS") else FAST_XLA
    start = time.monotonic()
    with tempfile.TemporaryFile("w+") as log:
        rc = subprocess.call([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                              str(path)], stdout=log, stderr=subprocess.STDOUT, env=env)
        log.seek(0)
        return path, rc, time.monotonic() - start, log.read()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="test files at a time (default: 2, or 1 on a one-core machine)")
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
    with ThreadPoolExecutor(args.jobs) as pool:
        futures = [pool.submit(_run, f) for f in _order(files)]  # started in this order
        for future in as_completed(futures):
            path, rc, secs, out = future.result()
            print(f"== {path.name} ({secs:.0f} s, {'passed' if rc == 0 else 'FAILED'})")
            print(out, end="", flush=True)
            if rc != 0:
                failed.append(path.name)
    total = time.monotonic() - start
    if failed:
        print(f"some test files FAILED ({', '.join(failed)}); {total:.0f} s")
        return 1
    print(f"all test files passed; {total:.0f} s with {args.jobs} at a time")
    return 0


if __name__ == "__main__":
    sys.exit(main())

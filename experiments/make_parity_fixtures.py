"""Write the golden run files of tests/test_redesign_parity.py (tests/data/parity).

The fixtures pin the behaviour of commit 03050be, the code before the package's redesign:
generate them only from a checkout whose dscpp_jax/, envs/ and pyproject.toml equal that
commit's, and never regenerate them from later code, or the test pins nothing. The script
refuses to write into tests/data/parity otherwise; `--out DIR` writes elsewhere, for instance
to check that two generations agree (`diff -r`, apart from the wall-clock columns).

It runs the test's own commands (tests/test_redesign_parity.py) on the CPU and keeps:

    single/metrics.csv, single/config.json           the single run, N_ITERS iterations
    group/group.json, group/s{0,1}/metrics.csv ...   the two-seed group
    old_checkpoint/                                  the single run's command stopped after
                                                     K_ITERS iterations: the whole run directory
    SOURCE.json                                      the commit and the commands

    PYTHONPATH=$PWD python experiments/make_parity_fixtures.py [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from tests import test_redesign_parity as P  # noqa: E402

SOURCE_COMMIT = "03050be"
PINNED_PATHS = ("dscpp_jax", "envs", "pyproject.toml")


def code_is_source_commit() -> bool:
    """Whether the code that runs equals SOURCE_COMMIT's (committed or not)."""
    r = subprocess.run(["git", "-C", ROOT, "diff", "--quiet", SOURCE_COMMIT, "--", *PINNED_PATHS])
    return r.returncode == 0


def run_all(work: str) -> dict:
    """Run the three commands under `work`; returns the commands as text."""
    single, group, old = (os.path.join(work, n) for n in ("single", "group", "old_checkpoint"))
    cmds = {"single": P.single_args(single), "group": P.group_args(group),
            "old_checkpoint": P.single_args(old, P.K_ITERS)}
    for name, args in cmds.items():   # one at a time, each compiling from scratch
        print(f"{name}: python -m dscpp_jax.cli {' '.join(args)}", flush=True)
        P.finish_cli(P.start_cli(args, os.path.join(work, f"{name}.log")), name)
    return {k: "python -m dscpp_jax.cli " + " ".join(v).replace(work + os.sep, "")
            for k, v in cmds.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=P.DATA, help="where to write (default: tests/data/parity)")
    args = ap.parse_args(argv)
    out = os.path.abspath(args.out)
    if out == os.path.abspath(P.DATA) and not code_is_source_commit():
        print(f"error: {', '.join(PINNED_PATHS)} differ from {SOURCE_COMMIT}; the fixtures pin "
              f"that commit's behaviour (use --out DIR to write elsewhere)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as work:
        commands = run_all(work)
        single = P.read_rows(os.path.join(work, "single", "metrics.csv"))
        old = P.read_rows(os.path.join(work, "old_checkpoint", "metrics.csv"))
        P.assert_rows_equal(old, single[:P.K_ITERS], "old checkpoint against the single run")
        if os.path.isdir(out):
            shutil.rmtree(out)
        os.makedirs(os.path.join(out, "single"))
        for f in ("metrics.csv", "config.json"):
            shutil.copy(os.path.join(work, "single", f), os.path.join(out, "single", f))
        os.makedirs(os.path.join(out, "group"))
        shutil.copy(os.path.join(work, "group", "group.json"), os.path.join(out, "group"))
        for s in (0, 1):
            os.makedirs(os.path.join(out, "group", f"s{s}"))
            for f in ("metrics.csv", "config.json"):
                shutil.copy(os.path.join(work, "group", f"s{s}", f),
                            os.path.join(out, "group", f"s{s}", f))
        shutil.copytree(os.path.join(work, "old_checkpoint"), os.path.join(out, "old_checkpoint"))
        for dirpath, _, files in os.walk(out):   # readable like any tracked file
            for f in files:
                os.chmod(os.path.join(dirpath, f), 0o644)
    source = {"commit": SOURCE_COMMIT, "platform": "cpu", "xla_flags": P.FIXTURE_XLA_FLAGS,
              "commands": commands}
    with open(os.path.join(out, "SOURCE.json"), "w") as f:
        json.dump(source, f, indent=2)
        f.write("\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

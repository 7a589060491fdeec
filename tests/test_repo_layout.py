"""The repository's documents: links resolve, and committed results are not ignored by git."""
import glob
import os
import re
import shutil
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _documents():
    pats = ["README.md", "docs/*.md", "experiments/results/**/*.md"]
    return sorted({f for p in pats for f in glob.glob(os.path.join(ROOT, p), recursive=True)})


def test_markdown_links_to_files_in_the_repo_resolve():
    broken = []
    for doc in _documents():
        with open(doc) as f:
            text = f.read()
        for m in LINK.finditer(text):
            target = m.group(1).split("#")[0]
            if not target or re.match(r"^[a-z]+:", target):
                continue
            if not os.path.exists(os.path.normpath(os.path.join(os.path.dirname(doc), target))):
                broken.append(f"{os.path.relpath(doc, ROOT)} -> {m.group(1)}")
    assert not broken, "broken links:\n" + "\n".join(broken)


@pytest.mark.parametrize("path", [
    "experiments/results/paper/runs/u_maze-dsc-g0-4/s0/metrics.csv",
    "experiments/results/some_study/runs/group/s0/eval.json",
    "experiments/results/some_study/runs_variant/group/s0/config.json",
])
def test_results_under_experiments_are_not_ignored(path):
    """Lean runs live under experiments/results/**/runs/; a repo-wide `runs/` rule once kept
    them out of every commit while the READMEs pointed at them."""
    if shutil.which("git") is None or not os.path.isdir(os.path.join(ROOT, ".git")):
        pytest.skip("not a git checkout")
    r = subprocess.run(["git", "check-ignore", "--no-index", "-q", path], cwd=ROOT)
    assert r.returncode == 1, f"{path} is ignored by git"


def test_scratch_run_directories_stay_ignored():
    if shutil.which("git") is None or not os.path.isdir(os.path.join(ROOT, ".git")):
        pytest.skip("not a git checkout")
    r = subprocess.run(["git", "check-ignore", "--no-index", "-q", "runs/u_maze/metrics.csv"],
                       cwd=ROOT)
    assert r.returncode == 0, "runs/ at the top level should be ignored"

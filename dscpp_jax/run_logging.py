"""Host-side run logging: metrics.csv (always), TensorBoard events (when tensorboardX is installed),
config.json with library versions."""
from __future__ import annotations

import csv
import json
import math
import os
import platform
import subprocess
import sys
from typing import Any, Mapping

BASE_COLUMNS = ("iteration", "env_steps", "episodes", "wall_clock")


def library_versions() -> dict[str, str]:
    """Versions of the libraries a run depends on (for config.json), the source's git commit when
    it runs from a checkout (``+dirty`` with uncommitted changes), and ``XLA_FLAGS``, which can
    change numerics (e.g. ``--xla_gpu_deterministic_ops=true``)."""
    out = {"python": sys.version.split()[0], "platform": platform.platform(),
           "xla_flags": os.environ.get("XLA_FLAGS", "")}
    commit = _git_commit(os.path.abspath(__file__))
    if commit:
        out["dscpp_jax_git"] = commit
    for mod in ("jax", "jaxlib", "flax", "optax", "chex", "orbax.checkpoint", "brax", "mujoco",
                "numpy", "dscpp_jax"):
        try:
            from importlib.metadata import version
            out[mod] = version(mod.replace(".", "-"))
        except Exception:  # noqa: BLE001 - not installed or no metadata
            continue
    try:
        import jax
        out["jax_backend"] = jax.default_backend()
        out["devices"] = ", ".join(str(d) for d in jax.devices())
    except Exception:  # noqa: BLE001
        pass
    return out


def _git_commit(source_file: str) -> str:
    """HEAD of the git checkout that tracks ``source_file`` (with ``+dirty`` if tracked files
    changed), or "" when it is not tracked by one (an installed copy) or git is missing."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", os.path.dirname(source_file), *args],
                              capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    try:
        git("ls-files", "--error-unmatch", source_file)  # fails unless this checkout tracks it
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+dirty" if dirty else "")


def write_config(run_dir: str, config_dict: Mapping[str, Any], extra: Mapping[str, Any] | None = None
                 ) -> None:
    payload = {"config": dict(config_dict), "versions": library_versions()}
    if extra:
        payload.update(extra)
    with open(os.path.join(run_dir, "config.json"), "w") as f:
        json.dump(payload, f, indent=2, sort_keys=True)


def read_config(run_dir: str) -> dict:
    with open(os.path.join(run_dir, "config.json")) as f:
        return json.load(f)


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    try:
        fv = float(v)
    except (TypeError, ValueError):
        return str(v)
    if math.isnan(fv):
        return ""
    if fv == int(fv) and abs(fv) < 1e15:
        return str(int(fv))
    return f"{fv:.6g}"


class RunLogger:
    """Appends one row per logged iteration to metrics.csv; mirrors scalars to TensorBoard.

    The column set is fixed by the first row (or by an existing file when resuming). On resume,
    rows past the restored iteration are dropped so the file matches the restored state.
    """

    def __init__(self, run_dir: str, columns: list[str] | None = None,
                 resume_iteration: int | None = None, tensorboard: bool = True):
        self.run_dir = run_dir
        self.path = os.path.join(run_dir, "metrics.csv")
        self.columns: list[str] | None = None
        if os.path.exists(self.path):
            with open(self.path, newline="") as f:
                rows = list(csv.reader(f))
            if rows:
                self.columns = rows[0]
                keep = [rows[0]]
                for r in rows[1:]:
                    if resume_iteration is None or (r and int(float(r[0])) <= resume_iteration):
                        keep.append(r)
                with open(self.path, "w", newline="") as f:
                    csv.writer(f).writerows(keep)
        if self.columns is None and columns is not None:
            self._start(columns)
        self.tb = None
        if tensorboard:
            try:
                from tensorboardX import SummaryWriter
                self.tb = SummaryWriter(os.path.join(run_dir, "tb"))
            except Exception:  # noqa: BLE001 - optional dependency
                self.tb = None

    def _start(self, columns: list[str]) -> None:
        self.columns = list(BASE_COLUMNS) + sorted(c for c in columns if c not in BASE_COLUMNS)
        with open(self.path, "w", newline="") as f:
            csv.writer(f).writerow(self.columns)

    def _extend(self, new: list[str]) -> None:
        """Add columns (e.g. the first evaluation's) by rewriting the file with a wider header."""
        with open(self.path, newline="") as f:
            rows = list(csv.reader(f))
        old = self.columns
        self.columns = list(BASE_COLUMNS) + sorted((set(old) | set(new)) - set(BASE_COLUMNS))
        idx = {c: i for i, c in enumerate(old)}
        with open(self.path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.columns)
            for r in rows[1:]:
                w.writerow([r[idx[c]] if c in idx and idx[c] < len(r) else "" for c in self.columns])

    def log(self, row: Mapping[str, Any]) -> None:
        if self.columns is None:
            self._start(list(row))
        new = [c for c in row if c not in self.columns]
        if new:
            self._extend(new)
        with open(self.path, "a", newline="") as f:
            csv.writer(f).writerow([_fmt(row.get(c)) for c in self.columns])
        if self.tb is not None:
            step = int(row.get("env_steps", 0))
            for k, v in row.items():
                if k in BASE_COLUMNS[:1]:
                    continue
                try:
                    fv = float(v)
                except (TypeError, ValueError):
                    continue
                if not math.isnan(fv):
                    self.tb.add_scalar(k, fv, step)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.flush()
            self.tb.close()
            self.tb = None


def read_metrics(run_dir: str) -> dict[str, list[float]]:
    """metrics.csv as columns of floats (blank cells are NaN)."""
    path = os.path.join(run_dir, "metrics.csv") if os.path.isdir(run_dir) else run_dir
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return {}
    cols = rows[0]
    out: dict[str, list[float]] = {c: [] for c in cols}
    for r in rows[1:]:
        for c, v in zip(cols, r):
            try:
                out[c].append(float(v) if v != "" else float("nan"))
            except ValueError:
                out[c].append(float("nan"))
    return out

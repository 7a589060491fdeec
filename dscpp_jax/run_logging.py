"""Host-side run logging: metrics.csv (always), TensorBoard events (when tensorboardX is installed),
Weights & Biases (on request, when wandb is installed), config.json with library versions; and
reading a run directory back with errors that say what is wrong with it."""
from __future__ import annotations

import csv
import errno
import io
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
import uuid
from importlib.metadata import version
from typing import Any, Mapping, Optional

import jax
import numpy as np

from dscpp_jax.config import Config
from dscpp_jax.options import STATUS_NAMES, TABLE_PREFIX

BASE_COLUMNS = ("iteration", "env_steps", "episodes", "wall_clock")
RUN_DIR_LAYOUT = ("a run directory, as `train` makes it, holds config.json, metrics.csv and "
                  "checkpoints/")
WANDB_ID_FILE = "wandb_run.json"
OPTIONS_FILE = "options.csv"
OPTIONS_COLUMNS = ("iteration", "env_steps", "option", "status", "parent", "executions",
                   "successes", "positives", "negatives")
OPTIONS_EVERY = 5   # iterations between two snapshots of the option table in options.csv


class RunDirError(ValueError):
    """A run directory that cannot be read or written; the message says what to do."""


class WandbError(ValueError):
    """Weights & Biases logging was asked for but cannot start; the message says what to do."""


def os_error_fix(e: BaseException, path: str, resume_dir: Optional[str] = None) -> str:
    """One sentence on why writing `path` failed and what to do about it (errno-aware; finds an
    OSError also where a library wrapped it)."""
    err, seen, visited = None, e, set()
    # the chain can loop: orbax raises one failed save's exception again at each later wait,
    # which makes it the context of an error raised while it was being handled
    while seen is not None and err is None and id(seen) not in visited:
        visited.add(id(seen))
        if isinstance(seen, OSError) and seen.errno:
            err = seen.errno
        seen = seen.__cause__ or seen.__context__
    text = str(e)
    again = f" and continue with `train --resume {resume_dir}`" if resume_dir else ""
    if err in (errno.ENOSPC, errno.EDQUOT) or "No space left" in text or "quota" in text.lower():
        return f"the disk holding {path} is full: free space on it{again}"
    if err in (errno.EROFS, errno.EACCES, errno.EPERM) or "Read-only" in text or \
            "Permission denied" in text:
        return (f"{path} is not writable: make it writable (or copy the run directory somewhere "
                f"writable){again}")
    return f"check the disk and the permissions of {path} ({text}){again}"


def current_umask() -> int:
    """This process's umask, read without changing it (Linux's /proc/self/status; elsewhere by
    setting it and back, which other threads could see for an instant)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: str, text: str) -> None:
    """Write `path` through a temporary file and a rename: a failed write (a full disk) leaves
    the old file as it was. The file gets the permissions `open` would give it (0666 less the
    umask), not the temporary file's 0600."""
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", dir=d)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "w", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


STARTUP_FILE = "startup.jsonl"


def process_age_s() -> Optional[float]:
    """Seconds since this process started (Linux, from /proc); None where that is not known."""
    try:
        with open("/proc/self/stat") as f:
            stat = f.read()
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        start_ticks = int(stat[stat.rindex(")") + 2:].split()[19])   # field 22: starttime
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return None


class StartupClock:
    """Where a training command's start goes, up to the end of its first iteration: with
    ``count_process``, the process's age when the clock starts (interpreter and imports: for a
    process that is the command), and named phases timed one after another (`mark` closes the
    phase that ran since the last mark). `write` appends one JSON line per command to the run
    directory's startup.jsonl (a resumed run adds one)."""

    def __init__(self, count_process: bool = True):
        self.before_s = process_age_s() if count_process else None
        self.started = time.time()
        self._last = self.started
        self.phases: dict = {}

    def mark(self, name: str) -> None:
        now = time.time()
        self.phases[name] = self.phases.get(name, 0.0) + (now - self._last)
        self._last = now

    def record(self, **extra) -> dict:
        timed = sum(self.phases.values())
        rec = {"started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(self.started)),
               "process_start_to_clock_s": None if self.before_s is None else round(self.before_s, 3),
               "phases_s": {k: round(v, 3) for k, v in self.phases.items()},
               "command_to_first_iteration_s": round(timed + (self.before_s or 0.0), 3)}
        rec.update(extra)
        return rec

    def line(self) -> str:
        """One line for the terminal: the total and the phases over a second."""
        rec = self.record()
        parts = ([f"process start {rec['process_start_to_clock_s']:.1f} s"]
                 if rec["process_start_to_clock_s"] is not None else [])
        parts += [f"{k} {v:.1f} s" for k, v in rec["phases_s"].items() if v >= 1.0]
        return (f"start-up: {rec['command_to_first_iteration_s']:.1f} s to the end of the first "
                f"iteration ({', '.join(parts)})")

    def write(self, run_dir: str, **extra) -> dict:
        """Append this command's record to run_dir/startup.jsonl as one line."""
        rec = self.record(**extra)
        path = os.path.join(run_dir, STARTUP_FILE)
        lead = ""
        try:   # a line cut short by a crash ends here, so that this record gets its own line
            with open(path, "rb") as f:
                f.seek(-1, os.SEEK_END)
                lead = "" if f.read(1) == b"\n" else "\n"
        except OSError:   # no file yet, or an empty one
            pass
        with open(path, "a") as f:
            f.write(lead + json.dumps(rec) + "\n")
        return rec


def read_startup(run_dir: str) -> list:
    """The start-up records of a run (or group) directory, oldest first; unreadable lines (a
    write cut short) are left out, and a directory without any gives []."""
    out = []
    try:
        with open(os.path.join(run_dir, STARTUP_FILE)) as f:
            for line in f:
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                if isinstance(rec, dict):
                    out.append(rec)
    except OSError:
        return []
    return out


def _csv_text(rows) -> str:
    buf = io.StringIO()
    csv.writer(buf).writerows(rows)
    return buf.getvalue()


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
            out[mod] = version(mod.replace(".", "-"))
        except Exception:  # noqa: BLE001 - not installed or no metadata
            continue
    try:
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
    """config.json: the config, library versions, and every Config default of this version
    ("config_defaults"), so that a later version that dropped a field knows its "off" value."""
    payload = {"config": dict(config_dict), "versions": library_versions(),
               "config_defaults": Config().to_dict()}
    if extra:
        payload.update(extra)
    atomic_write(os.path.join(run_dir, "config.json"), json.dumps(payload, indent=2, sort_keys=True))


def read_config(run_dir: str) -> dict:
    """config.json of a run directory; a RunDirError says what is wrong when it is not one."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.isdir(run_dir):
        what = "does not exist" if not os.path.exists(run_dir) else "is not a directory"
        raise RunDirError(f"run directory {run_dir} {what}: {RUN_DIR_LAYOUT} (e.g. "
                          f"runs/point_u_maze-mb_dscpp-s0-<time>); check the path")
    if not os.path.isfile(path):
        raise RunDirError(f"{run_dir} is not a run directory (it has no config.json): "
                          f"{RUN_DIR_LAYOUT}; pass the directory that `train` printed")
    try:
        with open(path) as f:
            payload = json.load(f)
    except OSError as e:
        raise RunDirError(f"cannot read {path} ({e.strerror or e}): make it readable") from None
    except ValueError as e:   # JSONDecodeError, UnicodeDecodeError
        raise RunDirError(f"{path} is not valid JSON ({e}): the run's config file is damaged or "
                          f"not one that `train` wrote; {RUN_DIR_LAYOUT}") from None
    if not isinstance(payload, dict) or not isinstance(payload.get("config"), dict):
        raise RunDirError(f"{path} has no \"config\" section: it is not the config file of a "
                          f"dscpp_jax run; {RUN_DIR_LAYOUT}")
    return payload


def load_config(run_dir: str):
    """The run's Config, checked against this version (see `Config.from_saved`)."""
    payload = read_config(run_dir)
    try:
        return Config.from_saved(payload["config"], payload.get("config_defaults"),
                                 source=f"run {run_dir}")
    except ValueError as e:
        raise RunDirError(str(e)) from None


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


def _keep_rows(path: str, resume_iteration: Optional[int]) -> Optional[list]:
    """The header of a CSV whose first column is the iteration, after dropping rows cut short
    (a full disk) and, on resume, rows past `resume_iteration` (rewriting the file if any went);
    None when the file does not exist or is empty."""
    if not os.path.exists(path):
        return None
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return None
    keep = [rows[0]]
    for r in rows[1:]:
        if len(r) != len(rows[0]):
            continue   # a row cut short (the disk filled up while it was written)
        if resume_iteration is None or (r and int(float(r[0])) <= resume_iteration):
            keep.append(r)
    if len(keep) != len(rows):
        atomic_write(path, _csv_text(keep))
    return rows[0]


class RunLogger:
    """Appends one row per logged iteration to metrics.csv; mirrors scalars to TensorBoard.
    A row's `table/*` columns (the option table, `options.table_columns`) go to options.csv
    instead, one line per option in use, every `OPTIONS_EVERY` iterations.

    The column set is fixed by the first row (or by an existing file when resuming). On resume,
    rows past the restored iteration are dropped from both files so they match the restored
    state.
    """

    def __init__(self, run_dir: str, columns: list[str] | None = None,
                 resume_iteration: int | None = None, tensorboard: bool = True,
                 wandb: Optional[Mapping[str, Any]] = None):
        self.run_dir = run_dir
        self.path = os.path.join(run_dir, "metrics.csv")
        self.options_path = os.path.join(run_dir, OPTIONS_FILE)
        self.columns: list[str] | None = _keep_rows(self.path, resume_iteration)
        _keep_rows(self.options_path, resume_iteration)
        if self.columns is None and columns is not None:
            self._start(columns)
        self.tb = None
        if tensorboard:
            try:
                from tensorboardX import SummaryWriter
                self.tb = SummaryWriter(os.path.join(run_dir, "tb"))
            except Exception:  # noqa: BLE001 - optional dependency
                self.tb = None
        self.wandb = None if wandb is None else start_wandb(run_dir, **wandb)

    def _start(self, columns: list[str]) -> None:
        self.columns = list(BASE_COLUMNS) + sorted(c for c in columns if c not in BASE_COLUMNS)
        atomic_write(self.path, _csv_text([self.columns]))

    def _extend(self, new: list[str]) -> None:
        """Add columns (e.g. the first evaluation's) by rewriting the file with a wider header."""
        with open(self.path, newline="") as f:
            rows = list(csv.reader(f))
        old = self.columns
        columns = list(BASE_COLUMNS) + sorted((set(old) | set(new)) - set(BASE_COLUMNS))
        idx = {c: i for i, c in enumerate(old)}
        out = [columns] + [[r[idx[c]] if c in idx and idx[c] < len(r) else "" for c in columns]
                           for r in rows[1:]]
        atomic_write(self.path, _csv_text(out))
        self.columns = columns

    def log_table(self, iteration: int, env_steps: float, table: Mapping[str, Any]) -> None:
        """options.csv lines of one snapshot of the option table (`table`: name -> (K,)), for
        the options in use."""
        cols = {k: np.asarray(v) for k, v in table.items()}
        status = cols["status"]
        lines = [] if os.path.exists(self.options_path) else [list(OPTIONS_COLUMNS)]
        for k in range(status.shape[0]):
            s = int(status[k])
            if s <= 0 or s >= len(STATUS_NAMES):
                continue   # a free row (or a frozen seed's NaN)
            lines.append([iteration, int(env_steps), k, STATUS_NAMES[s]]
                         + [int(cols[c][k]) for c in OPTIONS_COLUMNS[4:]])
        with open(self.options_path, "a", newline="") as f:
            csv.writer(f).writerows(lines)

    def log(self, row: Mapping[str, Any]) -> None:
        table = {k[len(TABLE_PREFIX):]: v for k, v in row.items() if k.startswith(TABLE_PREFIX)}
        if table:
            row = {k: v for k, v in row.items() if not k.startswith(TABLE_PREFIX)}
            it = int(row.get("iteration", 0))
            if it % OPTIONS_EVERY == 0:
                self.log_table(it, float(row.get("env_steps", 0)), table)
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
        if self.wandb is not None:
            vals = {}
            for k, v in row.items():
                try:
                    fv = float(v)
                except (TypeError, ValueError):
                    continue
                if not math.isnan(fv):
                    vals[k] = fv
            self.wandb.log(vals)

    def close(self) -> None:
        if self.tb is not None:
            try:
                self.tb.flush()
                self.tb.close()
            except Exception:  # noqa: BLE001 - never hide the error that ends a run
                pass
            self.tb = None
        if self.wandb is not None:
            try:
                self.wandb.finish()
            except Exception:  # noqa: BLE001
                pass
            self.wandb = None


def wandb_missing_error() -> Optional[str]:
    """None when wandb imports, else the one-line fix."""
    try:
        import wandb  # noqa: F401
    except ImportError:
        return ("--wandb needs the wandb package, which is not installed: pip install "
                "'dscpp_jax[wandb]' (or pip install wandb), or drop --wandb")
    return None


def start_wandb(run_dir: str, project: str = "dscpp_jax", mode: Optional[str] = None,
                config: Optional[Mapping[str, Any]] = None, name: Optional[str] = None):
    """A Weights & Biases run logging the same metric names as metrics.csv, against env_steps.

    The wandb run id is kept in RUN_DIR/wandb_run.json, so a resumed run continues the same wandb
    run. `mode`: online | offline | disabled (default: $WANDB_MODE, else online)."""
    missing = wandb_missing_error()
    if missing:
        raise WandbError(missing)
    import wandb
    id_path = os.path.join(run_dir, WANDB_ID_FILE)
    saved = {}
    if os.path.exists(id_path):
        try:
            with open(id_path) as f:
                saved = json.load(f)
        except (OSError, ValueError):
            saved = {}
    run_id = saved.get("id") or uuid.uuid4().hex[:12]
    if saved.get("project"):
        project = saved["project"]
    if not saved:
        atomic_write(id_path, json.dumps({"id": run_id, "project": project}, indent=2))
    mode = mode or os.environ.get("WANDB_MODE") or "online"
    try:
        run = wandb.init(project=project, id=run_id, resume="allow", mode=mode,
                         name=name or os.path.basename(os.path.normpath(run_dir)),
                         config=dict(config or {}), dir=os.environ.get("WANDB_DIR") or run_dir)
    except Exception as e:  # noqa: BLE001 - wandb raises its own types (no login, no network)
        raise WandbError(f"could not start Weights & Biases in {mode} mode ({type(e).__name__}: "
                         f"{' '.join(str(e).split())[:300]}): run `wandb login`, or log locally "
                         f"with --wandb-mode offline (sync later with `wandb sync`)") from None
    run.define_metric("env_steps")
    run.define_metric("*", step_metric="env_steps")
    return run


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

"""PNG plots: trajectories coloured by option (paper Figure 1), each option's optimistic region and
pessimistic contour (appendix Figure 1), and success rate / number of options over training from
metrics.csv for one or many runs (mean +- standard error; paper Figure 6, appendix Figure 3)."""
from __future__ import annotations

import json
import os
import sys
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.patches import Rectangle
from matplotlib.ticker import FuncFormatter, MaxNLocator

from dscpp_jax import seed_group as SG
from dscpp_jax import svm
from dscpp_jax.checkpoint import NoCheckpointError
from dscpp_jax.config import HOST_ONLY_DEFAULTS, Config
from dscpp_jax.evaluate import evaluate
from dscpp_jax.run_dir import is_group_dir, load_run, seed_dirs
from dscpp_jax.run_logging import read_config, read_metrics
from dscpp_jax.trainer import make_env


def _plt():
    """pyplot on the Agg back end, chosen when the first plot is drawn (not when this module is
    imported, so that importing the package leaves an interactive session's back end alone)."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def draw_maze(ax, layout):
    """The maze of `layout` (MazeLayout) on axes `ax`: walls, bounds, start and goal."""
    for cx, cy, hx, hy in layout.wall_boxes:
        ax.add_patch(Rectangle((cx - hx, cy - hy), 2 * hx, 2 * hy, color="0.35", zorder=1))
    xmin, xmax, ymin, ymax = layout.bounds
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.plot(*layout.start_xy, "o", color="tab:green", ms=8, zorder=5, label="start")
    ax.plot(*layout.goal_xy, "*", color="gold", mec="k", ms=16, zorder=5, label="goal")


def option_color(option: int, max_options: int) -> tuple:
    """RGBA (floats) of an option index in the trajectory plots (and the videos); -1 (no option
    running) is grey."""
    if option < 0:
        return (0.5, 0.5, 0.5, 1.0)
    cmap = _plt().get_cmap("tab10" if max_options <= 10 else "tab20")
    return tuple(float(c) for c in cmap(int(option) % cmap.N))


def maze_layout(cfg):
    """The MazeLayout of the environment that `cfg` trains on."""
    return make_env(cfg).layout


def plot_trajectory(cfg, result, path: str, title: str = "", max_episodes: int = 4) -> str:
    """Executed trajectories (EvalResult) over the maze, each segment coloured by its option.

    Failed episodes are drawn first (up to half of `max_episodes`), and where every failed episode
    ended is marked: a red x, or a red triangle when the body ended on its back.
    """
    plt = _plt()
    xy = np.asarray(result.xy)            # (L+1, N, 2)
    opt = np.asarray(result.option)       # (L, N)
    act = np.asarray(result.active)       # (L, N)
    succ_e = np.asarray(result.success).astype(bool)
    upright = np.asarray(result.upright)
    fails, wins = np.flatnonzero(~succ_e), np.flatnonzero(succ_e)
    n_f = min(len(fails), max(max_episodes // 2, max_episodes - len(wins)))
    drawn = list(fails[:n_f]) + list(wins[:max_episodes - n_f])
    K = int(cfg.chain.max_options)
    cmap = plt.get_cmap("tab10" if K <= 10 else "tab20")
    fig, ax = plt.subplots(figsize=(7.6, 6))
    draw_maze(ax, maze_layout(cfg))
    used = set()
    for e in drawn:
        m = act[:, e] & (opt[:, e] >= 0)
        seg = np.stack([xy[:-1, e], xy[1:, e]], axis=1)[m]
        o = opt[m, e]
        used.update(int(v) for v in np.unique(o))
        lc = LineCollection(seg, colors=[cmap(int(v) % cmap.N) for v in o], linewidths=2, zorder=3)
        ax.add_collection(lc)
    for o in sorted(used):
        name = {0: "global", 1: "goal option"}.get(o, f"option {o}")
        ax.plot([], [], color=cmap(o % cmap.N), lw=3, label=name)
    if len(fails):
        end = xy[-1]
        flip = upright[fails] < 0
        ax.scatter(end[fails[~flip], 0], end[fails[~flip], 1], marker="x", c="red", s=40,
                   zorder=5, label=f"failed, end ({int((~flip).sum())})")
        if flip.any():
            ax.scatter(end[fails[flip], 0], end[fails[flip], 1], marker="v", c="red", s=40,
                       zorder=5, label=f"failed on its back ({int(flip.sum())})")
    # beside the maze, never over it (on the larger mazes every spot inside holds a corridor)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize=7)
    ax.set_title(title or f"{cfg.env} {cfg.algo}", fontsize=10)
    ax.set_xlabel(f"x   (success {succ_e.mean():.0%} of {xy.shape[1]} episodes; "
                  f"{len(drawn)} drawn, {n_f} failed)")
    ax.set_ylabel("y")
    _save(fig, path)
    return path


def plot_classifiers(cfg, state, path: str, resolution: int = 80) -> str:
    """Each fitted option's optimistic region (filled) and pessimistic region (black contour),
    titled with its parent and how many of its training executions succeeded (all so far)."""
    plt = _plt()
    layout = maze_layout(cfg)
    chain = state.chain
    if chain is None:
        fig, ax = plt.subplots(figsize=(5, 5))
        draw_maze(ax, layout)
        ax.set_title(f"{cfg.algo}: flat agent, no options")
        _save(fig, path)
        return path
    status = np.asarray(chain.status)
    fitted = np.asarray(chain.fitted)
    rows = [k for k in range(1, status.shape[0]) if status[k] != 0 and fitted[k]]
    xmin, xmax, ymin, ymax = layout.bounds
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, resolution), np.linspace(ymin, ymax, resolution))
    grid = jnp.asarray(np.stack([gx.ravel(), gy.ravel()], -1), jnp.float32)
    ncol = max(1, min(4, len(rows)))
    nrow = max(1, -(-len(rows) // ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 3.6 * nrow), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    dec = jax.jit(jax.vmap(svm.decision_function, in_axes=(0, None)))
    for i, k in enumerate(rows):
        ax = axes.ravel()[i]
        ax.axis("on")
        clf = jax.tree_util.tree_map(lambda a: a[k], chain.clf)
        opt = np.asarray(dec(jax.tree_util.tree_map(lambda a: a[None], clf.optimistic), grid))[0]
        pes = np.asarray(dec(jax.tree_util.tree_map(lambda a: a[None], clf.pessimistic), grid))[0]
        opt = opt.reshape(gx.shape) if bool(clf.optimistic_fitted) else np.full(gx.shape, -1.0)
        pes = pes.reshape(gx.shape) if bool(clf.pessimistic_fitted) else np.full(gx.shape, -1.0)
        draw_maze(ax, layout)
        ax.contourf(gx, gy, (opt > 0).astype(float), levels=[0.5, 1.5], colors=["tab:red"],
                    alpha=0.45, zorder=2)
        if (pes > 0).any() and (pes < 0).any():
            ax.contour(gx, gy, pes, levels=[0.0], colors="k", linewidths=1.5, zorder=4)
        pos = np.asarray(chain.pos_xy[k])[np.asarray(chain.pos_mask[k])]
        if pos.size:
            ax.scatter(pos[::7, 0], pos[::7, 1], s=2, c="tab:blue", zorder=3)
        name = "goal option" if k == 1 else f"option {k} (-> {int(chain.parent[k])})"
        st = {1: "gestation", 2: "mature"}.get(int(status[k]), "")
        ok, tried = int(chain.successes[k]), int(chain.executions[k])
        ax.set_title(f"{name}, {st}\n{ok} of {tried} executions succeeded", fontsize=9)
        ax.legend().set_visible(False) if ax.get_legend() else None
    fig.suptitle(f"{cfg.env} {cfg.algo}: optimistic (red) and pessimistic (black) regions",
                 fontsize=10)
    _save(fig, path, rect=(0, 0, 1, 1 - 0.35 / (3.6 * nrow)))   # the suptitle above the titles
    return path


def metric_curve(run_dir: str, column: str, x_column: str = "env_steps"):
    """(x, y) of metrics.csv's `column` against `x_column` in RUN_DIR, the rows where both are
    finite (in-band rows only once a window finished); None when there are none."""
    try:
        m = read_metrics(run_dir)
    except FileNotFoundError:   # a run that has not logged an iteration yet
        return None
    if column not in m or x_column not in m:
        return None
    x = np.asarray(m[x_column], float)
    y = np.asarray(m[column], float)
    ok = np.isfinite(y) & np.isfinite(x)
    if column.startswith("inband/") and "inband/window" in m:   # none finished yet: no figure
        ok &= np.asarray(m["inband/window"], float) > 0
    return (x[ok], y[ok]) if ok.any() else None


def _group_runs(run_dirs: Sequence[str]) -> dict:
    """Runs whose configs differ only in the seed (and host-side schedule fields) form one group,
    named "<env> <algo>"; where several groups share env and algo, the fields that tell them
    apart are appended (e.g. "u_maze mb_dscpp td3_batch_size=1024")."""
    runs_of: dict[str, list[str]] = {}
    cfg_of: dict[str, dict] = {}
    for r in run_dirs:
        try:
            # fields added after a run was made take their defaults, the value that run used
            payload = read_config(r)
            full = Config.from_dict(payload["config"]).flat()
            c = {k: v for k, v in full.items() if k not in HOST_ONLY_DEFAULTS}
            # the env's own settings (physics), where the run recorded them
            c.update({f"env.{k}": v for k, v in payload.get("env", {}).items()})
        except Exception:  # noqa: BLE001
            runs_of.setdefault(os.path.basename(os.path.normpath(r)), []).append(r)
            continue
        key = json.dumps(c, sort_keys=True)
        cfg_of[key] = c
        runs_of.setdefault(key, []).append(r)
    groups: dict[str, list[str]] = {}
    for key, runs in runs_of.items():
        c = cfg_of.get(key)
        if c is None:
            groups[key] = runs
            continue
        name = f"{c['env']} {c['algo']}" + (" (dp)" if c.get("subgoal") == "dp" else "")
        same = [o for o in cfg_of.values() if o["env"] == c["env"] and o["algo"] == c["algo"]]
        diff = sorted(k for k in c if any(o.get(k) != c[k] for o in same)
                      and not (k.startswith("env.") and any(k not in o for o in same)))
        if diff:
            name += " " + " ".join(f"{k}={c[k]}" for k in diff)
        groups.setdefault(name, []).extend(runs)
    return groups


def split_label(entry: str) -> tuple[Optional[str], str]:
    """"LABEL=RUN_DIR" -> (LABEL, RUN_DIR); a plain run directory -> (None, entry). The label may
    hold "=", the path not (a directory whose own name has "=" stays a plain entry)."""
    label, sep, run = str(entry).rpartition("=")
    if sep and not os.path.isdir(str(entry)):
        return label, run
    return None, str(entry)


def _si(v: float) -> str:
    """1500 -> '1.5k', 2_000_000 -> '2M' (tick labels for step counts)."""
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= div:
            return f"{v / div:.3g}{unit}"
    return f"{v:.3g}"


def plot_curves(run_dirs: Sequence[str], path: str, group: bool = True) -> str:
    """Eval success from the start vs env steps, episodes and wall-clock (and, dashed, in-band
    success where the runs logged it), and the number of options and training-episode success
    vs env steps. Runs that differ only in the seed are
    grouped: mean +- standard error on a common grid (see `_group_runs`). An entry "LABEL=RUN_DIR"
    puts that run in the group LABEL instead (runs with the same label are averaged; the path is
    what follows the last "=")."""
    plt = _plt()
    labelled: dict[str, list[str]] = {}
    plain = []
    for r in run_dirs:
        label, run = split_label(r)
        if label is not None:
            labelled.setdefault(label, []).append(run)
        else:
            plain.append(run)
    missing = [r for rs in labelled.values() for r in rs] + plain
    missing = [r for r in missing if not os.path.isdir(r)]
    if missing:
        raise ValueError(f"not a run directory: {', '.join(missing)}")
    for r in [r for rs in labelled.values() for r in rs] + plain:
        read_config(r)   # a RunDirError saying what is wrong with a directory that is no run
    groups = _group_runs(plain) if group else {
        os.path.basename(os.path.normpath(r)): [r] for r in plain}
    groups.update(labelled)
    panels = [("env_steps", "eval/success_rate", "eval success rate (from the start)"),
              ("episodes", "eval/success_rate", "eval success rate (from the start)"),
              ("wall_clock", "eval/success_rate", "eval success rate (from the start)"),
              ("env_steps", "options/num_options", "number of options"),
              ("env_steps", "train/episode_success", "training episode success")]
    xlabels = {"env_steps": "env steps", "episodes": "training episodes",
               "wall_clock": "wall-clock (s)"}
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4 + 0.3 * ((len(groups) + 1) // 2)))
    colors = {name: f"C{i % 10}" for i, name in enumerate(groups)}
    for (xcol, col, ylabel), ax in zip(panels, axes):
        # runs with in-band evaluation also show its success, every iteration, dashed
        cols = [(col, "-", "")] + ([("inband/success_rate", "--", " in-band")]
                                   if col == "eval/success_rate" else [])
        for name, runs in groups.items():
            for c_col, style, suffix in cols:
                curves = [c for c in (metric_curve(r, c_col, xcol) for r in runs) if c is not None]
                if not curves:
                    continue
                xmax = min(c[0][-1] for c in curves)
                grid = np.unique(np.concatenate([c[0][c[0] <= xmax] for c in curves]))
                ys = np.stack([np.interp(grid, c[0], c[1]) for c in curves])
                mean = ys.mean(0)
                ax.plot(grid, mean, style, color=colors[name],
                        label=f"{name}{suffix} (n={len(curves)})")
                if len(curves) > 1:
                    se = ys.std(0, ddof=1) / np.sqrt(len(curves))
                    ax.fill_between(grid, mean - se, mean + se, color=colors[name], alpha=0.25)
        ax.set_xlabel(xlabels[xcol])
        if xcol == "env_steps":   # 200k, 1.5M: raw step counts run into each other
            ax.xaxis.set_major_locator(MaxNLocator(nbins=6))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: _si(v)))
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if col.endswith("success_rate") or col.endswith("episode_success"):
            ax.set_ylim(-0.03, 1.03)
    handles, names = axes[0].get_legend_handles_labels()
    if handles:  # below the panels, where long group names cover no data
        fig.legend(handles, names, loc="lower center", ncol=min(len(names), 2), fontsize=9,
                   frameon=False)
    rows = (len(names) + 1) // 2
    _save(fig, path, rect=(0, min(0.4, 0.07 * rows), 1, 1) if handles else None)
    return path


def plot_seeds(run_dirs: Sequence[str], path: str, cols: int = 5) -> str:
    """One small panel per run (e.g. each seed of a group): evaluation success from the start
    (periodic evaluations, markers; the final evaluation of eval.json, a star) and in-band
    success (dashed) vs training episodes. The mean curves of `plot_curves` hide what a single
    seed does: whether its chain held once it worked, or dipped and recovered."""
    plt = _plt()
    runs = [split_label(r) for r in run_dirs]
    n = len(runs)
    cols = max(1, min(cols, n))
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.4 * rows), squeeze=False,
                             sharex=True, sharey=True)
    for ax, (label, run) in zip(axes.flat, runs):
        name = label or os.path.basename(os.path.normpath(run))
        ev = metric_curve(run, "eval/success_rate", "episodes")
        ib = metric_curve(run, "inband/success_rate", "episodes")
        if ib is not None:
            ax.plot(ib[0], ib[1], "--", color="C1", lw=1, label="in-band")
        if ev is not None:
            ax.plot(ev[0], ev[1], "-o", color="C0", ms=2.5, lw=1, label="evaluation")
        final = ""
        try:
            with open(os.path.join(run, "eval.json")) as f:
                e = json.load(f)
            if "episodes_trained" in e:
                ax.plot([e["episodes_trained"]], [e["eval/success_rate"]], "*", color="C3",
                        ms=9, label="final evaluation")
            final = f", final {e['eval/success_rate']:.2f}"
        except (OSError, ValueError, KeyError):
            pass
        ax.set_title(f"{name}{final}", fontsize=9)
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("training episodes")
    for ax in axes[:, 0]:
        ax.set_ylabel("success from the start")
    handles, names = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, names, loc="lower center", ncol=len(names), fontsize=9, frameon=False)
    _save(fig, path, rect=(0, 0.06 if rows > 1 else 0.12, 1, 1) if handles else None)
    return path


def expand_groups(entries: Sequence[str]) -> list[str]:
    """Each seed-group directory among `entries` ("LABEL=DIR" too) replaced by its seeds'
    directories, in the group's seed order; run directories stay as they are."""
    out = []
    for e in entries:
        label, run = split_label(e)
        if os.path.isdir(run) and is_group_dir(run):
            out += [f"{label}={d}" if label is not None else d for d in seed_dirs(run)]
        else:
            out.append(e)
    return out


def plot_runs(run_dirs: Sequence[str], out_dir: str, with_state: bool = True,
              trajectory: bool = True) -> list[str]:
    """All plots for the given runs (a seed group's directory stands for its seeds): curves (and
    for several runs one panel per run, seeds.png); with ``with_state`` also each run's classifiers and (``trajectory``: after evaluation
    episodes from its checkpoint) trajectories. A run without a checkpoint (a results copy)
    gets its curves and a line on stderr saying why nothing else."""
    run_dirs = expand_groups(run_dirs)
    os.makedirs(out_dir, exist_ok=True)
    paths = [plot_curves(run_dirs, os.path.join(out_dir, "curves.png"))]
    if len(run_dirs) > 1:   # one panel per run as well
        paths.append(plot_seeds(run_dirs, os.path.join(out_dir, "seeds.png")))
    if with_state:
        for r in run_dirs:
            r = split_label(r)[1]
            tag = "" if len(run_dirs) == 1 else os.path.basename(os.path.normpath(r)) + "_"
            try:
                cfg, state = load_run(r)
            except NoCheckpointError:
                print(f"{r}: no checkpoint, so only its curves (the options' regions and "
                      f"trajectories come from a checkpoint)", file=sys.stderr)
                continue
            if trajectory:
                _, res = evaluate(state, jax.random.PRNGKey(0), max(4, cfg.eval.episodes))
                it = int(state.counters.iteration)
                paths.append(plot_trajectory(
                    cfg, res, os.path.join(out_dir, f"{tag}trajectory.png"),
                    title=f"{cfg.env} {cfg.algo}, iteration {it}, "
                          f"{int(state.counters.env_steps)} env steps"))
            paths.append(plot_classifiers(cfg, state, os.path.join(out_dir, f"{tag}classifiers.png")))
    return paths


def _save(fig, path: str, rect=None) -> None:
    d = os.path.dirname(path)
    if d:
        os.makedirs(d, exist_ok=True)
    fig.tight_layout(rect=rect)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    _plt().close(fig)


def plot_run(run_dir: str, cfg, state, res) -> list[str]:
    """The plots of a run at the end of its schedule (`train --plot`), in RUN_DIR/plots: its
    curves, the trajectories of its final evaluation `res` and its options' classifiers."""
    out = os.path.join(run_dir, "plots")
    it = int(state.counters.iteration)
    return [plot_curves([run_dir], os.path.join(out, "curves.png")),
            plot_trajectory(cfg, res, os.path.join(out, "trajectory.png"),
                            title=f"{cfg.env} {cfg.algo}, iteration {it}, "
                                  f"{int(state.counters.env_steps)} env steps"),
            plot_classifiers(cfg, state, os.path.join(out, "classifiers.png"))]


def plot_group(group_dir: str, cfgs, dirs, host, res) -> None:
    """The plots of a seed group at the end of its schedule (`group_train.train_group`'s `plot`):
    curves over the seeds in GROUP/plots, and each seed's curves, trajectory and classifiers in
    its own plots/, from the group's host copy `host` and its final evaluation `res`."""
    c = host.counters
    n = len(dirs)
    plot_curves(dirs, os.path.join(group_dir, "plots", "curves.png"))
    for i, (cfg, d) in enumerate(zip(cfgs, dirs)):
        out = os.path.join(d, "plots")
        plot_curves([d], os.path.join(out, "curves.png"))
        plot_trajectory(cfg, SG.index_tree(res, i), os.path.join(out, "trajectory.png"),
                        title=f"{cfg.env} {cfg.algo} seed {cfg.run.seed}, iteration "
                              f"{int(c.iteration[i])}, {int(c.env_steps[i])} env steps")
        plot_classifiers(cfg, SG.index_tree(host, i, n), os.path.join(out, "classifiers.png"))

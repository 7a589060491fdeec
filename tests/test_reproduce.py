"""experiments/reproduce.py end to end on tiny point-mass configs: two algorithms (and MF-DSC++
with one critic per option for appendix Figure 2), two seeds, a few iterations each; every figure
that has runs is drawn with its CSV, the README checks each claim, and a second call trains nothing
(finished groups are skipped)."""
import csv
import hashlib
import json
import os
import shutil
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "experiments"))
import reproduce  # noqa: E402
from dscpp_jax.config import flat_config  # noqa: E402

sys.path.pop(0)


def _flat(cfg):
    """A config as runs saved it before the sections: flat."""
    return cfg.flat()

TINY = ["num_envs=4", "steps_per_iter=20", "episode_length=100", "warmup_episodes=2",
        "max_options=4", "max_pos_traj=8", "max_neg=8", "buffer_len=10", "option_timeout=40",
        "gestation=2", "td3_hidden=32", "td3_batch_size=32", "td3_updates_per_step=0.1",
        "replay_capacity=2000", "eval_episodes=2", "eval_every=2", "checkpoint_every=2"]


def _args(runs, out, *extra):
    a = ["--fig", "all", "--env-map", "u_maze=point_u_maze",
         "--env-map", "ant_reacher=point_ant_reacher", "--mazes", "u_maze",
         "--algos", "dsc,mf_dscpp", "--fig4-algo", "mf_dscpp", "--seeds", "0-1",
         "--a1-seeds", "0-1", "--episodes", "8", "--fig4-episodes", "8", "--jobs", "2",
         "--a1-resolution", "24", "--a1-every", "3", "--runs-root", runs, "--out", out]
    for s in TINY:
        a += ["--set", s]
    return a + list(extra)


def _metrics(runs):
    out = {}
    for root, _, files in os.walk(runs):
        if "metrics.csv" in files:
            p = os.path.join(root, "metrics.csv")
            out[p] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return out


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


# XLA's CPU backend without its expensive LLVM passes, for the six training calls (subprocesses,
# which inherit the environment): compiling is most of their time, and the checks below read what
# was trained, drawn and reported, never the numbers themselves. About 40 % less CPU time per call.
FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"


def test_reproduce_trains_draws_reports_then_skips(tmp_path, capsys, monkeypatch):
    # XLA reads its flags when this process's backend starts: start it first, so that only the
    # train subprocesses compile without optimisation and later tests here are not affected
    import jax
    jax.devices()
    monkeypatch.setenv("XLA_FLAGS", f"{os.environ.get('XLA_FLAGS', '')} {FAST_COMPILE}".strip())
    runs, out = str(tmp_path / "runs"), str(tmp_path / "out")
    assert reproduce.main(_args(runs, out)) == 0
    text = capsys.readouterr().out
    # Figure 4's robust group is also A1's DSC++ group (same seeds), and A2's shared-critic arm is
    # Figures 5 and 6's MF-DSC++ group: six groups, each trained once
    assert text.count(": started") == 6 and text.count(": finished (") == 6
    assert "point_u_maze-mf_dscpp-g0-1-optcritic: started" in text
    opt = json.load(open(os.path.join(runs, "point_u_maze-mf_dscpp-g0-1-optcritic",
                                      "group.json")))["config"]
    opt = flat_config(opt)
    assert opt["shared_critic"] is False and opt["algo"] == "mf_dscpp"
    for fig in ("fig4", "fig5", "fig6", "figA1", "figA2", "figA3"):
        assert os.path.getsize(os.path.join(out, fig + ".png")) > 1000, fig
        assert _rows(os.path.join(out, fig + ".csv")), fig
    f6 = _rows(os.path.join(out, "fig6.csv"))
    assert {r["algo"] for r in f6} == {"dsc", "mf_dscpp"}
    assert {r["n_seeds"] for r in f6} == {"2"} and {r["finished"] for r in f6} == {"1"}
    assert {r["env"] for r in _rows(os.path.join(out, "fig5.csv"))} == {"point_u_maze"}
    f4 = _rows(os.path.join(out, "fig4.csv"))
    assert len(f4) == 2 * 2 * 4   # subgoals x seeds x corners
    assert {(r["start_x"], r["start_y"]) for r in f4} == {
        (str(x), str(y)) for x, y in reproduce.CORNERS}
    for r in f4:   # the sparse return: -(steps) plus the final step's 0 on success
        assert float(r["return"]) == -(int(r["steps"]) - int(r["success"]))
    a1 = _rows(os.path.join(out, "figA1.csv"))
    assert {r["algo"] for r in a1} == {"dsc", "mf_dscpp"}
    assert len({r["checkpoint"] for r in a1 if r["algo"] == "dsc"}) >= 3   # kept over training
    a1_cfg = json.load(open(os.path.join(runs, "point_ant_reacher-dsc-g0-1", "group.json")))
    assert a1_cfg["config"]["run"]["checkpoint_every"] == 3   # --a1-every, not --set's 2
    a2 = _rows(os.path.join(out, "figA2.csv"))
    assert {(r["algo"], r["critic"]) for r in a2} == {("mf_dscpp", "shared"),
                                                      ("mf_dscpp", "per_option")}
    assert {r["env"] for r in a2} == {"point_u_maze"} and {r["n_seeds"] for r in a2} == {"2"}

    readme = open(os.path.join(out, "README.md")).read()
    assert readme.startswith("# The paper's figures, reproduced on other environments "
                             "(u_maze -> point_u_maze, ant_reacher -> point_ant_reacher)")
    claims_part = readme.split("## Claims", 1)[1].split("## Figures", 1)[0]
    table = [l for l in claims_part.splitlines()
             if l.startswith("| ") and not l.startswith("| figure")]
    figs = [l.split("|")[1].strip() for l in table]
    times = readme.split("Training time", 1)[1].splitlines()
    assert any(l.startswith("| all (each group once) | 6 |") for l in times)
    assert set(figs) == {"4", "5", "6", "A1", "A2", "A3"}
    ok = ("reproduced", "not reproduced", "incomplete (runs missing or not finished)", "not run")
    for line in table:
        status = line.rstrip(" |").rsplit("|", 1)[1].strip()
        assert status.startswith(ok), line
    a2 = next(l for l in table if l.startswith("| A2 |"))
    assert "one shared critic" in a2 and "one critic per option" in a2 and "point_u_maze" in a2
    assert a2.endswith(("| reproduced |", "| not reproduced |"))   # both arms finished
    assert "not implemented" not in readme and "![Figure A2](figA2.png)" in readme \
        and "[`figA2.csv`](figA2.csv)" in readme
    # only two of Figure 6's six algorithms ran: that claim cannot be settled
    assert any(l.startswith("| 6 | u_maze: MB-DSC++ and MF-DSC++ outperform") and "incomplete"
               in l for l in table)
    assert any(l.startswith("| 6 | u_maze: both flat") and l.endswith("| not run |")
               for l in table)
    # every group with a skill chain says how its seeds end (diagnose's verdicts)
    why = [l for l in readme.splitlines() if l.startswith("- `point_") and " runs: " in l]
    assert {l.split("`")[1] for l in why} >= {"point_u_maze-mf_dscpp-g0-1",
                                               "point_u_maze-dsc-g0-1"}, why
    for l in why:
        counts = [int(c.split(" ", 1)[0]) for c in l.split(" runs: ")[1].split("; ")]
        assert sum(counts) == int(l.split(" runs: ")[0].rsplit(" ", 1)[1]) == 2, l

    # a second call finds every group finished: no training, metrics untouched
    before = _metrics(runs)
    assert len(before) == 12   # 6 groups x 2 seeds
    assert reproduce.main(_args(runs, out)) == 0
    text = capsys.readouterr().out
    assert text.count("skipped (finished)") == 6
    assert ": started" not in text and ": resumed" not in text
    assert _metrics(runs) == before

    # a lean copy of the runs (metrics, config, eval.json: what committed results keep, without
    # checkpoints) is finished too, and reports as the runs do
    lean = str(tmp_path / "lean")
    assert reproduce.main(_args(runs, out, "--report-only", "--export-lean", lean)) == 0
    capsys.readouterr()
    kept = {os.path.relpath(os.path.join(r, f), lean) for r, _, fs in os.walk(lean) for f in fs}
    assert not any("checkpoints" in k for k in kept)
    assert os.path.join("point_u_maze-dsc-g0-1", "s1", "metrics.csv") in kept
    assert os.path.join("logs", "point_u_maze-dsc-g0-1.log") in kept
    assert sum(k.endswith("reproduce_fig4.npz") for k in kept) == 4   # 2 subgoals x 2 seeds
    assert reproduce.main(_args(lean, out, "--fig", "5,6,A3", "--dry-run")) == 0
    text = capsys.readouterr().out
    assert text.count("skipped (finished)") == 2 and "would" not in text
    # ... and, with the cached evaluations kept beside each seed, draws Figure 4 and appendix
    # Figure 1 without checkpoints, with the same numbers
    lean_out = str(tmp_path / "lean_out")
    assert reproduce.main(_args(lean, lean_out, "--report-only")) == 0
    capsys.readouterr()
    # a page drawn without training says so (its command would train nothing)
    assert "Drawn from the runs as they are" in open(os.path.join(lean_out, "README.md")).read()
    for fig in ("fig4", "figA1"):
        assert os.path.getsize(os.path.join(lean_out, fig + ".png")) > 1000, fig
        assert _rows(os.path.join(lean_out, fig + ".csv")) == _rows(os.path.join(out, fig + ".csv"))
    shutil.rmtree(lean_out)
    for root, _, files in os.walk(lean):   # a lean copy without them: not drawn, not claimed
        for f in files:
            if f.startswith("reproduce_") and f.endswith(".npz"):
                os.remove(os.path.join(root, f))
    assert reproduce.main(_args(lean, lean_out, "--report-only")) == 0
    text = capsys.readouterr().out
    assert "figure 4: no runs yet" in text and "figure A1: no runs yet" in text
    assert not os.path.exists(os.path.join(lean_out, "fig4.png"))

    # a longer schedule continues a group from its checkpoint; a directory without a checkpoint
    # (killed before its first) is started again
    os.makedirs(os.path.join(runs, "point_u_maze-dual-g0-1", "s0"))
    assert reproduce.main(_args(runs, out, "--fig", "5", "--algos", "dsc,dual", "--episodes",
                                "16", "--dry-run")) == 0
    text = capsys.readouterr().out
    group = os.path.join(runs, "point_u_maze-dsc-g0-1")
    line = next(l for l in text.splitlines() if "point_u_maze-dsc-g0-1: would resume" in l)
    assert f"python -m dscpp_jax.cli train --resume {group} --total-episodes 16" in line
    # a resume may change only the schedule and host-side cadences
    assert "--set eval_every=2" in line and "--set checkpoint_every=2" in line
    assert "num_envs" not in line and "--algo" not in line
    assert "point_u_maze-dual-g0-1: would start: " in text and "--algo dual" in text

    # a call killed after logging its last iteration but before saving it (eval.json, written
    # after the last checkpoint, is older than metrics.csv) is not finished
    ev = os.path.join(runs, "point_u_maze-mf_dscpp-g0-1", "s1", "eval.json")
    e = json.load(open(ev))
    e["iteration"] -= 1
    json.dump(e, open(ev, "w"))
    assert reproduce.main(_args(runs, out, "--fig", "5", "--dry-run")) == 0
    text = capsys.readouterr().out
    assert "point_u_maze-mf_dscpp-g0-1: would resume" in text
    assert "point_u_maze-dsc-g0-1: skipped (finished)" in text


def test_train_calls_spread_over_gpus(tmp_path, capsys, monkeypatch):
    # several visible GPUs and no --gpus: one GPU per train call (a 5-seed group cannot be split
    # over two)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    assert reproduce.visible_gpus() == ["2", "3"]
    runs, out = str(tmp_path / "runs"), str(tmp_path / "out")
    assert reproduce.main(["--fig", "5", "--runs-root", runs, "--out", out, "--dry-run"]) == 0
    assert "2 GPUs: each train call takes one of them (--gpus 2,3 --jobs 2" in \
        capsys.readouterr().out
    # a job given GPUs 2 and 3 cannot send a train call to GPU 0
    assert reproduce.main(["--fig", "5", "--gpus", "0", "--runs-root", runs, "--dry-run"]) == 2
    assert "--gpus 0: 0 not in CUDA_VISIBLE_DEVICES=2,3" in capsys.readouterr().err
    assert reproduce.main(["--fig", "5", "--gpus", "3", "--runs-root", runs, "--dry-run"]) == 0
    capsys.readouterr()
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "-1")
    assert reproduce.visible_gpus() == []
    assert reproduce.main(["--fig", "5", "--gpus", ",", "--dry-run"]) == 2
    assert "names no GPU" in capsys.readouterr().err
    assert reproduce.gpu_slots(["0", "1"], 4) == ["0", "1", "0", "1"]
    assert reproduce.gpu_slots(["3"], 1) == ["3"]
    assert reproduce.gpu_slots(["0", "1", "2"], 2) == ["0", "1"]
    with pytest.raises(ValueError, match="no GPU"):
        reproduce.gpu_slots([], 2)


@pytest.mark.parametrize("argv, says", [
    (["--algos", "foo"], "--algos 'foo': unknown 'foo'; choose from"),
    (["--algos", ","], "--algos ',': names nothing"),
    (["--mazes", "bogus"], "--mazes 'bogus': unknown 'bogus'; choose from u_maze, medium, large"),
    (["--episodes", "0"], "--episodes 0: give a whole number >= 1"),
    (["--fig4-episodes", "-5"], "--fig4-episodes -5"),
    (["--jobs", "0"], "--jobs 0"),
    (["--env-map", "u_maze"], "--env-map 'u_maze': write PAPER=ENV"),
    (["--env-map", "u_maze=pointy"], "--env-map 'u_maze=pointy': write PAPER=ENV"),
    (["--set", "foo=1"], "unknown config field 'foo'"),
    (["--set", "num_envs=abc"], "num_envs is an integer"),
    (["--fig4-algo", "td3_her"], "--fig4-algo 'td3_her'"),
    (["--a1-every", "0"], "--a1-every 0"),
])
def test_bad_arguments_stop_before_anything_runs(tmp_path, capsys, argv, says):
    runs = str(tmp_path / "runs")
    assert reproduce.main(["--fig", "all", "--runs-root", runs, "--dry-run"] + argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and says in err and "Traceback" not in err
    assert not os.path.exists(runs)


def test_bad_figure_and_a2_only(tmp_path, capsys, monkeypatch):
    assert reproduce.main(["--fig", "7"]) == 2
    assert "unknown figure" in capsys.readouterr().err
    out, runs = str(tmp_path / "out"), str(tmp_path / "runs")
    # appendix Figure 2 alone: the shared-critic group (named as Figures 5 and 6 name it) and its
    # own one-critic-per-option group
    assert reproduce.main(["--fig", "A2", "--runs-root", runs, "--out", out, "--dry-run"]) == 0
    text = capsys.readouterr().out
    lines = [l for l in text.splitlines() if ": would start: " in l]
    assert len(lines) == 2
    shared, = [l for l in lines if "u_maze-mf_dscpp-g0-4: would start" in l]
    per, = [l for l in lines if "u_maze-mf_dscpp-g0-4-optcritic: would start" in l]
    assert "shared_critic" not in shared and "--set shared_critic=false" in per
    assert "--env u_maze --algo mf_dscpp" in per
    monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "unset")   # restored after the test
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE")
    assert reproduce.main(["--fig", "A2", "--runs-root", runs, "--out", out,
                           "--report-only"]) == 0
    # the figures' own JAX work does not take most of every visible GPU up front
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    readme = open(os.path.join(out, "README.md")).read()
    assert readme.count("| not run") == readme.count("\n| ") - 1   # every claim: not run
    # a hand-written "## Notes" section survives the next call
    with open(os.path.join(out, "README.md"), "a") as f:
        f.write("\n## Notes\n\nWhat these runs mean.\n")
    assert reproduce.main(["--fig", "A2", "--runs-root", runs, "--out", out,
                           "--report-only"]) == 0
    readme = open(os.path.join(out, "README.md")).read()
    assert readme.count("## Notes") == 1 and readme.endswith("\n## Notes\n\nWhat these runs mean.\n")
    assert readme.startswith("# The paper's figures, reproduced\n")


def test_success_curves_come_from_in_band_evaluation_where_runs_have_it(tmp_path):
    """Runs with in-band evaluation (the ant preset's default) draw success from
    `inband/success_rate` (rows before the first finished in-band episode left out); the final
    success of a claim stays the last evaluation's."""
    from dscpp_jax.run_logging import RunLogger
    inb, per = str(tmp_path / "inband"), str(tmp_path / "periodic")
    for d, rows in ((inb, [dict(inband_w=0, inband=0.0), dict(inband_w=4, inband=0.5),
                           dict(inband_w=4, inband=0.75, ev=0.9)]),
                    (per, [dict(ev=0.25), dict(), dict(ev=0.5)])):
        log = RunLogger(d)
        for i, r in enumerate(rows, 1):
            row = {"iteration": i, "env_steps": 100 * i, "episodes": 10 * i}
            if "inband" in r:
                row.update({"inband/success_rate": r["inband"], "inband/window": r["inband_w"]})
            if "ev" in r:
                row["eval/success_rate"] = r["ev"]
            log.log(row)
        log.close()
    (x, y), = reproduce.curves([inb], "eval/success_rate")
    assert x.tolist() == [20.0, 30.0] and y.tolist() == [0.5, 0.75]
    (x, y), = reproduce.curves([inb], "eval/success_rate", inband=False)
    assert x.tolist() == [30.0] and y.tolist() == [0.9]
    (x, y), = reproduce.curves([per], "eval/success_rate")
    assert x.tolist() == [10.0, 30.0] and y.tolist() == [0.25, 0.5]


def test_final_success_comes_from_eval_json_of_the_last_iteration(tmp_path):
    """A run that evaluates only in-band has no evaluation column in metrics.csv; its final
    success is eval.json's (the 100 episodes at the end), but only if eval.json is from the
    run's last logged iteration."""
    from dscpp_jax.run_logging import RunLogger
    dirs = []
    for i, (it, rate) in enumerate(((3, 0.83), (3, 0.0))):
        d = str(tmp_path / f"s{i}")
        log = RunLogger(d)
        for j in (1, 2, 3):
            log.log({"iteration": j, "env_steps": 100 * j, "episodes": 10 * j,
                     "inband/success_rate": 0.5, "inband/window": 4})
        log.close()
        with open(os.path.join(d, "eval.json"), "w") as f:
            json.dump({"eval/success_rate": rate, "iteration": it}, f)
        dirs.append(d)
    assert reproduce.final_evals(dirs, "eval/success_rate").tolist() == [0.83, 0.0]
    assert reproduce.final_evals(dirs, "eval/steps_to_goal") is None
    with open(os.path.join(dirs[1], "eval.json"), "w") as f:     # from an older iteration
        json.dump({"eval/success_rate": 1.0, "iteration": 2}, f)
    assert reproduce.final_evals(dirs, "eval/success_rate") is None
    assert reproduce.final_evals([], "eval/success_rate") is None


def test_long_td3_line_reads_the_final_evaluation(tmp_path):
    """Figure 6's dashed line (TD3+HER after 12,000 episodes) is the mean of each seed's final
    success: eval.json for runs that evaluate only in-band (the ant preset), the last periodic
    evaluation otherwise; no line without either."""
    from dscpp_jax.run_logging import RunLogger
    ant, point, bare = [], [], []
    for i, rate in enumerate((1.0, 0.0, 0.5)):
        for kind, dirs in (("ant", ant), ("point", point), ("bare", bare)):
            d = str(tmp_path / kind / f"s{i}")
            log = RunLogger(d)
            for j in (1, 2):
                row = {"iteration": j, "env_steps": 100 * j, "episodes": 10 * j,
                       "inband/success_rate": 0.25, "inband/window": 4}
                if kind == "point":
                    row["eval/success_rate"] = rate if j == 2 else 0.0
                log.log(row)
            log.close()
            if kind == "ant":
                with open(os.path.join(d, "eval.json"), "w") as f:
                    json.dump({"eval/success_rate": rate, "iteration": 2}, f)
            dirs.append(d)
    assert reproduce.final_success(ant).tolist() == [1.0, 0.0, 0.5]
    assert reproduce.final_success(point).tolist() == [1.0, 0.0, 0.5]
    assert reproduce.final_success(bare) is None


def test_an_algorithm_keeps_its_colour_in_every_panel(tmp_path, monkeypatch):
    """Figure 6's panels hold different sets of algorithms (a maze may lack a baseline's runs);
    each algorithm must be drawn in the same colour in all of them."""
    import types
    from dscpp_jax.run_logging import RunLogger
    plt = reproduce._plt()
    figs = []

    class Recorder:                    # pyplot that keeps the figures curve_figure closes
        def __getattr__(self, name):
            return getattr(plt, name)

        def subplots(self, *a, **k):
            fig, axes = plt.subplots(*a, **k)
            figs.append(fig)
            return fig, axes

        def close(self, *a):
            pass

    monkeypatch.setattr(reproduce, "_plt", lambda: Recorder())
    exps = {(m, a): reproduce.Exp(m, a, 10, "0") for m in ("u_maze", "medium")
            for a in ("dsc", "mb_dscpp")}
    dirs = {}
    for e in exps.values():
        d = str(tmp_path / f"{e.env}-{e.algo}")
        log = RunLogger(d)
        for i in (1, 2):
            log.log({"iteration": i, "env_steps": 100 * i, "episodes": 5 * i,
                     "eval/success_rate": 0.5})
        log.close()
        dirs[e] = [d]
    data = types.SimpleNamespace(args=types.SimpleNamespace(env_map={}),
                                 dirs=lambda e: dirs.get(e, []), finished=lambda e: True)
    panels = [("U-maze", [exps["u_maze", "dsc"], exps["u_maze", "mb_dscpp"]]),
              ("medium", [exps["medium", "mb_dscpp"]])]      # no DSC runs on this panel
    assert reproduce.curve_figure(data, panels, "eval/success_rate", "success",
                                  str(tmp_path / "f.png"), str(tmp_path / "f.csv"))
    colours = [{ln.get_label().split(" (")[0]: ln.get_color() for ln in ax.get_lines()}
               for ax in figs[0].axes]
    assert colours[0]["MB-DSC++"] == colours[1]["MB-DSC++"] != colours[0]["DSC"]
    plt.close(figs[0])


def test_stop_after_bounds_the_whole_call(tmp_path, capsys, monkeypatch):
    """--stop-after: each train call gets what is left of the call's time as its --time-budget
    (never more than --time-budget), and none starts with less than --min-call left."""
    clock = [1000.0]
    calls = []

    def fake_call(cmd, **kw):          # a train call that takes 700 s of the clock
        calls.append(cmd)
        clock[0] += 700
        return 0

    monkeypatch.setattr(reproduce.time, "time", lambda: clock[0])
    monkeypatch.setattr(reproduce.subprocess, "call", fake_call)
    runs, out = str(tmp_path / "runs"), str(tmp_path / "out")
    args = ["--fig", "5", "--runs-root", runs, "--out", out, "--jobs", "1", "--gpus", "0",
            "--stop-after", "1500", "--min-call", "300"]
    assert reproduce.main(args + ["--time-budget", "900"]) == 0
    budgets = [float(c[c.index("--time-budget") + 1]) for c in calls]
    assert budgets == [900, 800]            # 1500 - 700 left for the second call
    text = capsys.readouterr().out
    assert text.count("not started: 100s left of --stop-after") == 2    # the last two groups
    assert reproduce.main(args + ["--stop-after", "0"]) == 2
    assert "--stop-after 0: give a number of seconds > 0" in capsys.readouterr().err


def test_an_ordering_needs_more_than_one_standard_error():
    # the ant's medium maze: MF-DSC++ 0.16 ± 0.16 against DSC 0.14 ± 0.14 is a tie
    mf, dsc = np.array([0, 0, 0, 0.8, 0]), np.array([0, 0.71, 0, 0, 0])
    assert not reproduce.above(mf, dsc) and not reproduce.above(dsc, mf)
    # U-maze: 0.91 ± 0.01 against 0.88 ± 0.01 is an ordering, one way only
    mf = np.array([0.89, 0.94, 0.90, 0.89, 0.92])
    dsc = np.array([0.89, 0.91, 0.89, 0.83, 0.86])
    assert reproduce.above(mf, dsc) and not reproduce.above(dsc, mf)
    # one seed each (no spread): the plain order of the values
    assert reproduce.above(np.array([0.2]), np.array([0.1]))
    assert not reproduce.above(np.array([0.1]), np.array([0.1]))


def test_appendix_figure_1_counts_from_the_first_fitted_checkpoint():
    # the ant's goal option (seed 0): a checkpoint of the warm-up (no region yet), then fitted
    dsc = [(137, 12.3, 12.3), (482, 23.0, 23.0), (1003, 12.1, 12.1)]
    ours = [(0, 0.0, 0.0), (223, 137.5, 17.3), (712, 50.3, 19.3), (1005, 52.9, 21.1)]
    text, ok = reproduce.a1_verdict({"dsc": dsc, "mb_dscpp": ours}, "mb_dscpp")
    assert ok and "optimistic 138 -> 52.9, pessimistic 17.3 -> 21.1 (episodes 223 -> 1005)" in text
    # the earlier sample: the pessimistic region shrank from its first fitted checkpoint
    ours = [(237, 140.0, 23.5), (1009, 43.1, 20.9)]
    assert not reproduce.a1_verdict({"dsc": dsc, "mb_dscpp": ours}, "mb_dscpp")[1]
    # DSC's region as large as ours at the end: not reproduced either
    ours = [(223, 137.5, 10.0), (1005, 52.9, 12.1)]
    assert not reproduce.a1_verdict({"dsc": dsc, "mb_dscpp": ours}, "mb_dscpp")[1]


def test_appendix_figure_1_panels_start_at_the_first_fitted_checkpoint(tmp_path):
    # cached regions of a lean copy: the warm-up's checkpoint 5 holds none, 10 only a pessimistic
    # one, 15 both; no checkpoint there, so nothing is recomputed
    d = str(tmp_path)
    gx, gy = np.meshgrid(np.linspace(-1, 1, 4), np.linspace(-1, 1, 4))
    empty, some = -np.ones_like(gx), np.where(gx > 0, 1.0, -1.0)
    for step, opt, pes in ((5, empty, empty), (10, empty, some), (15, some, some)):
        np.savez(os.path.join(d, f"reproduce_a1_{step}.npz"), step=np.asarray(step),
                 episodes=np.asarray(step * 10), gx=gx, gy=gy, opt=opt, pes=pes)
    steps = reproduce.cached_a1_steps(d)
    assert steps == [5, 10, 15]
    assert reproduce._from_first_fitted(d, steps, 4, False) == [10, 15]
    assert reproduce._from_first_fitted(d, [5], 4, False) == [5]   # nothing fitted: keep them


def test_one_train_call_can_take_several_gpus(tmp_path, capsys, monkeypatch):
    # the 12,000-episode TD3+HER group split over four GPUs (groups are never padded)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    runs, out = str(tmp_path / "runs"), str(tmp_path / "out")
    base = ["--fig", "6", "--mazes", "u_maze", "--algos", "td3_her", "--long-td3",
            "--long-td3-episodes", "30", "--episodes", "20", "--runs-root", runs, "--out", out]
    assert reproduce.main(base + ["--long-td3-seeds", "0-7", "--gpus", "0+1+2+3"]) == 2
    err = capsys.readouterr().err
    assert ("u_maze-td3_her-g0-4: 5 seeds do not split evenly over the 4 GPUs of --gpus entry "
            "0+1+2+3") in err
    for bad in ("0+0", "0+a", "1+"):
        assert reproduce.main(base + ["--gpus", bad, "--dry-run"]) == 2
        assert f"--gpus entry {bad!r}" in capsys.readouterr().err
    assert not os.path.exists(runs)
    calls = []

    def fake_call(cmd, cwd, env, stdout, stderr):
        calls.append((cmd, env["CUDA_VISIBLE_DEVICES"]))
        return 1

    monkeypatch.setattr(reproduce.subprocess, "call", fake_call)
    reproduce.main(base + ["--seeds", "0-3", "--long-td3-seeds", "0-7", "--gpus", "0+1+2+3"])
    text = capsys.readouterr().out
    assert "u_maze-td3_her-g0-7-long: started on GPUs 0,1,2,3" in text
    assert sorted((c[c.index("--seeds") + 1], gpus) for c, gpus in calls) == [
        ("0-3", "0,1,2,3"), ("0-7", "0,1,2,3")]
    # the report finds the long group by its directory, whatever its seeds
    os.makedirs(os.path.join(runs, "u_maze-td3_her-g0-7-long"))
    args = reproduce.build_parser().parse_args(["--runs-root", runs])
    args.env_map = {}
    assert reproduce.long_td3_seeds(args) == "0-7"
    args.long_td3_seeds = "0-3"
    assert reproduce.long_td3_seeds(args) == "0-3"
    # a finished 5-seed group is only skipped: it does not stop the long group's 8 seeds
    runs2 = str(tmp_path / "runs2")
    shutil.copytree(os.path.join(reproduce.ROOT, "experiments", "results", "paper", "runs",
                                 "u_maze-td3_her-g0-4"), os.path.join(runs2, "u_maze-td3_her-g0-4"))
    calls.clear()
    reproduce.main(["--fig", "6", "--mazes", "u_maze", "--algos", "td3_her", "--long-td3",
                    "--long-td3-seeds", "0-7", "--gpus", "0+1+2+3", "--runs-root", runs2,
                    "--out", out])
    assert "u_maze-td3_her-g0-4: skipped (finished)" in capsys.readouterr().out
    assert [(c[c.index("--seeds") + 1], gpus) for c, gpus in calls] == [("0-7", "0,1,2,3")]


def test_driver_trains_td3_in_float32_and_older_groups_still_match(tmp_path):
    """The committed paper runs trained TD3 in float32, which the ant preset no longer does for
    model-free learners: the driver asks for float32 in every group, and a group made before
    `td3_dtype` existed (no such field in its group.json) counts as float32, not as a mismatch.
    Likewise the ant U-maze groups planned with 4,096 MPC samples, the preset's 2,048 since."""
    args = reproduce.build_parser().parse_args(["--runs-root", str(tmp_path), "--out", str(tmp_path)])
    args.env_map = {}
    exp = reproduce.Exp("four_rooms", "mf_dscpp", 2001, "0-4")
    cmd = " ".join(reproduce.train_command(exp, str(tmp_path / "g"), args, resume=False))
    assert "--set td3_dtype=float32" in cmd
    from dscpp_jax.config import preset
    cfg = _flat(preset("fast", "four_rooms", "mf_dscpp"))
    assert cfg["td3_dtype"] == "bfloat16"   # what the preset alone would give
    gdir = tmp_path / "grp"
    gdir.mkdir()

    def mismatch(config):
        (gdir / "group.json").write_text(json.dumps({"seeds": [0], "config": config}))
        return reproduce.config_mismatch(str(gdir), exp, args)

    older = {k: v for k, v in cfg.items() if k != "td3_dtype"}
    assert mismatch(older) == []
    assert mismatch({**cfg, "td3_dtype": "float32"}) == []
    assert mismatch(cfg) == ["td3_dtype='bfloat16' (asked: 'float32')"]
    # the user's --set still wins over the driver's own
    args.set = ["td3_dtype=bfloat16"]
    assert mismatch(cfg) == [] and "--set td3_dtype=bfloat16" in " ".join(
        reproduce.train_command(exp, str(tmp_path / "g"), args, resume=False))
    # the ant U-maze groups plan with 4,096 MPC samples, as committed; other envs as the preset
    args.set = []
    u = reproduce.Exp("u_maze", "mb_dscpp", 2001, "0-4")
    assert "--set mpc_samples=4096" in " ".join(
        reproduce.train_command(u, str(tmp_path / "g"), args, resume=False))
    assert "mpc_samples" not in cmd
    ucfg = _flat(preset("fast", "u_maze", "mb_dscpp"))
    (gdir / "group.json").write_text(json.dumps({"seeds": [0], "config": ucfg}))
    assert reproduce.config_mismatch(str(gdir), u, args) == ["mpc_samples=2048 (asked: 4096)"]
    args.env_map = {"u_maze": "point_u_maze"}     # the point twin keeps its own preset
    assert "mpc_samples" not in " ".join(
        reproduce.train_command(u, str(tmp_path / "g"), args, resume=False))


def test_a_group_made_before_a_preset_change_is_a_mismatch(tmp_path):
    """The driver compares a group's whole config with what the preset gives now, not only the
    fields a call names: a medium-maze group made before the preset turned on the chain's frontier
    is told apart (and left as it is), a group made after matches, and the host's resolved
    physics back end is no mismatch."""
    from dscpp_jax.config import preset
    args = reproduce.build_parser().parse_args(["--runs-root", str(tmp_path), "--out", str(tmp_path)])
    args.env_map = {}
    exp = reproduce.Exp("medium", "mb_dscpp", 2001, "0-4")
    gdir = tmp_path / "grp"
    gdir.mkdir()

    def mismatch(config):
        (gdir / "group.json").write_text(json.dumps({"seeds": [0, 1], "config": config}))
        return reproduce.config_mismatch(str(gdir), exp, args)

    now = dict(_flat(preset("fast", "medium", "mb_dscpp", td3_dtype="float32")),
               physics="warp", seed=1, total_episodes=1000, eval_every=5)
    assert mismatch(now) == []
    before = {k: v for k, v in now.items() if not k.startswith("frontier_")}
    before["max_options"] = 24
    bad = mismatch(before)
    assert "frontier_start_prob=0.0 (asked: 0.5)" in bad and "max_options=24 (asked: 32)" in bad
    assert len(bad) == 5, bad
    # the user's --set still decides: asking for the paper's rule matches the older group (the
    # frontier's radii, without effect in both, do not count)
    args.set = ["frontier_start_prob=0", "frontier_parent=false", "max_options=24"]
    assert mismatch(before) == []
    args.set = ["frontier_start_prob=0", "max_options=24"]    # frontier parents still on
    assert mismatch(before) == ["frontier_parent=False (asked: True)",
                                "frontier_radius=5.0 (asked: 6.0)"]
    args.set = ["physics=mjx"]     # a back end the call names is compared
    assert mismatch(now) == ["physics='warp' (asked: 'mjx')"]
    # a 32-row frontier group made before MB-DSC++ got one TD3 step per transition there
    args.set = []
    assert mismatch(dict(now, td3_updates_per_step=0.25)) == [
        "td3_updates_per_step=0.25 (asked: 1.0)"]


def test_protocol_line_names_what_the_preset_adds_beyond_the_paper():
    import types
    args = reproduce.build_parser().parse_args(["--runs-root", "r", "--out", "o"])
    args.env_map = {}
    plan = reproduce.plan(_ns(args, fig="6", algos="dsc,mb_dscpp,mf_dscpp,td3_her"))
    data = types.SimpleNamespace(info=plan["6"])
    note = reproduce._frontier_note(data, args)
    assert ("medium-mb_dscpp: `max_options=24 frontier_start_prob=0.0 frontier_parent=false "
            "td3_updates_per_step=0.25`") in note
    assert "four_rooms-mf_dscpp: `frontier_start_prob=0.0 frontier_parent=false`" in note
    assert "medium-dsc" not in note and "u_maze-" not in note     # nothing to turn off
    assert ("medium: the chain's frontier, more option rows, MB-DSC++ more TD3 steps per "
            "transition, MF-DSC++ the medium maze's TD3") in note
    assert "MF-DSC++ and TD3+HER keep the preset's action penalty" in note
    data.info = [reproduce.Exp("u_maze", a, 2001, "0-4") for a in ("dsc", "dual", "mb_dscpp")]
    assert reproduce._frontier_note(data, args) == ""      # U-maze: nothing beyond the paper


def _ns(args, **kw):
    import argparse
    return argparse.Namespace(**{**vars(args), **kw})


def test_figures_compare_at_the_papers_rule_and_show_dscpp_beyond_it_beside():
    """Figures 5, 6, A2 and A3 use groups at the paper's rule: the baselines' own groups (the
    preset gives them nothing beyond the paper) and, where the preset gives DSC++ (or TD3+HER on
    the medium maze) more, `-paperrule` groups with it off; Figure 6 adds DSC++'s preset groups
    as panels beyond the paper."""
    args = reproduce.build_parser().parse_args(["--runs-root", "r", "--out", "o"])
    args.env_map = {}
    plan = reproduce.plan(_ns(args, fig="5,6,A2,A3"))
    names = {f: [e.name({}) for e in es if not e.beyond] for f, es in plan.items()}
    assert names["5"] == names["A3"] == [f"u_maze-{a}-g0-4" for a in reproduce.FIG5_ALGOS]
    assert names["A2"] == ["u_maze-mf_dscpp-g0-4", "u_maze-mf_dscpp-g0-4-optcritic"]
    six = set(names["6"])
    assert {"medium-dsc-g0-4", "four_rooms-dsc-g0-4", "medium-mb_dscpp-g0-4-paperrule",
            "medium-mf_dscpp-g0-4-paperrule", "four_rooms-mb_dscpp-g0-4-paperrule",
            "four_rooms-mf_dscpp-g0-4-paperrule", "medium-td3_her-g0-4-paperrule",
            "four_rooms-td3_her-g0-4", "u_maze-mf_dscpp-g0-4"} <= six
    beyond = [e.name({}) for e in plan["6"] if e.beyond]
    assert beyond == ["medium-mb_dscpp-g0-4", "medium-mf_dscpp-g0-4", "four_rooms-mb_dscpp-g0-4",
                      "four_rooms-mf_dscpp-g0-4"]
    from dscpp_jax.config import preset
    for e in plan["6"]:
        cfg = preset("fast", e.env, e.algo, **reproduce._overrides(reproduce._sets(e, args)))
        assert cfg.frontier_on == e.beyond, e
        if e.env == "medium" and not e.beyond:
            assert (cfg.td3.her_strategy, cfg.td3.her_relabel_prob) == ("final", 0.5), e
    # on the point-mass twins nothing is beyond the paper: the preset's own groups
    args.env_map = {m: "point_" + m for m in reproduce.MAZES}
    plan = reproduce.plan(_ns(args, fig="6"))
    assert not any(e.beyond or e.tag for e in plan["6"])


def test_print_commands_lists_the_groups_to_train(tmp_path, capsys):
    """One train command per group still to train, with its run directory and the memory share
    for running them side by side; a paper's-rule group made under the preset's own name (before
    the preset had the settings beyond the paper) serves, and finished groups are left out."""
    from dscpp_jax.config import preset
    from dscpp_jax.run_logging import RunLogger
    runs = tmp_path / "runs"
    made = _flat(preset("fast", "four_rooms", "mb_dscpp", td3_dtype="float32",
                                     frontier_start_prob=0.0, frontier_parent=False))
    g = runs / "four_rooms-mb_dscpp-g0-4"
    g.mkdir(parents=True)
    (g / "group.json").write_text(json.dumps({"seeds": [0, 1, 2, 3, 4], "config": made}))
    for s in range(5):
        log = RunLogger(str(g / f"s{s}"))
        log.log({"iteration": 3, "env_steps": 10 ** 7, "episodes": 2001})
        log.close()
        (g / f"s{s}" / "eval.json").write_text(json.dumps({"iteration": 3}))
    argv = ["--fig", "5,6,A2,A3", "--print-commands", "--runs-root", str(runs),
            "--time-budget", "600"]
    assert reproduce.main(argv) == 0
    text = capsys.readouterr().out
    cmds = [l for l in text.splitlines() if not l.startswith("#")]
    assert text.startswith(f"# {len(cmds)} group(s) to train")
    assert all(l.startswith("XLA_PYTHON_CLIENT_MEM_FRACTION=") and
               " python -m dscpp_jax.cli train --env " in l and "--time-budget 600" in l
               and "--set td3_dtype=float32" in l for l in cmds)
    dirs = [l.split("--run-dir ")[1].split(" ")[0] for l in cmds]
    assert not any(d.endswith("four_rooms-mb_dscpp-g0-4-paperrule") for d in dirs)  # it serves
    assert str(runs / "u_maze-dsc-g0-4") in dirs and str(runs / "u_maze-dual-g0-4") in dirs
    assert str(runs / "u_maze-mf_dscpp-g0-4-optcritic") in dirs
    assert str(runs / "medium-mb_dscpp-g0-4-paperrule") in dirs
    assert not any(d.endswith("four_rooms-mb_dscpp-g0-4") for d in dirs)
    # the preset's group with the frontier (beyond the paper) is not trained unless asked
    assert reproduce.main(argv + ["--beyond-paper"]) == 0
    text = capsys.readouterr().out
    assert "# four_rooms-mb_dscpp-g0-4: made with other settings" in text
    assert "# medium-mb_dscpp-g0-4 (start)" in text


def test_medium_model_free_learners_share_one_td3_configuration():
    """On the medium maze MF-DSC++ and TD3+HER get the same TD3 (HER `future` at 0.8, the action
    penalty of 2), DSC++'s chains 32 rows; the paper's baselines, the model-based learners and
    the other mazes keep the ant preset's."""
    from dscpp_jax.config import MEDIUM_MODEL_FREE_TD3, MODEL_BASED_ALGOS, preset
    td3 = lambda c: (c.td3.her_strategy, c.td3.her_relabel_prob, c.td3.action_l2, c.td3.updates_per_step,
                     c.td3.batch_size, c.td3.lr, c.td3.dtype)
    free = [preset("fast", "medium", a) for a in ("mf_dscpp", "td3_her")]
    assert len({td3(c) for c in free}) == 1
    assert td3(free[0])[:3] == ("future", 0.8, 2.0) == tuple(MEDIUM_MODEL_FREE_TD3[k] for k in (
        "her_strategy", "her_relabel_prob", "td3_action_l2"))
    assert [c.chain.max_options for c in free] == [32, 24]
    for a in ("dsc", "dual"):          # the paper's baselines: nothing beyond the paper
        c = preset("fast", "medium", a)
        assert td3(c)[:3] == ("final", 0.5, 0.0) and c.chain.max_options == 24
    for a in MODEL_BASED_ALGOS:
        c = preset("fast", "medium", a)
        assert (c.td3.her_strategy, c.td3.action_l2) == ("final", 0.0)
    assert preset("fast", "medium", "mb_dscpp").chain.max_options == 32
    for env in ("u_maze", "four_rooms", "large", "point_medium"):
        c = preset("fast", env, "mf_dscpp")
        assert c.td3.her_strategy == "final" and c.td3.action_l2 != 2.0
    # a user's --set still wins
    assert preset("fast", "medium", "mf_dscpp", her_strategy="final").td3.her_strategy == "final"


def test_readme_lists_groups_made_with_other_settings(tmp_path):
    """A group on disk whose config differs from what the call would train it with is named in
    the generated README with the fields that differ; a matching group is not."""
    import types
    from dscpp_jax.config import preset
    args = reproduce.build_parser().parse_args(["--runs-root", str(tmp_path), "--out", str(tmp_path)])
    args.env_map = {}
    old, new = (reproduce.Exp("medium", a, 2001, "0-4") for a in ("td3_her", "mb_dscpp"))
    info = {}
    for exp, cfg in ((old, dict(_flat(preset("fast", "medium", "td3_her",
                                                          td3_dtype="float32")),
                                her_strategy="final", td3_action_l2=1.0)),
                     (new, _flat(preset("fast", "medium", "mb_dscpp", td3_dtype="float32")))):
        gdir = tmp_path / exp.name({})
        gdir.mkdir()
        (gdir / "group.json").write_text(json.dumps({"seeds": [0], "config": cfg}))
        info[exp] = dict(dir=str(gdir), seeds=[], name=f"`{exp.name({})}`")
    info[reproduce.Exp("u_maze", "dsc", 2001, "0-4")] = dict(dir=str(tmp_path / "none"), seeds=[],
                                                             name="`u_maze-dsc-g0-4`")
    lines = reproduce.mismatch_lines(types.SimpleNamespace(info=info), args)
    assert lines == ["- `medium-td3_her-g0-4`: her_strategy='final' (asked: 'future'); "
                     "td3_action_l2=1.0 (asked: 2.0)"]


def test_a_figure_takes_its_seeds_from_a_larger_group(tmp_path, capsys):
    """Seeds 0-1 of a finished 4-seed group `point_u_maze-dsc-g0-3` serve a figure that asks for
    seeds 0-1 when no `-g0-1` group exists: its two seed directories are drawn, the group is
    skipped as finished, and a group named after the asked seeds wins where there is one. A
    larger group with nothing to resume does not take the asked seeds' training."""
    from dscpp_jax.config import preset
    from dscpp_jax.run_logging import RunLogger
    cfg = _flat(preset("fast", "point_u_maze", "dsc", td3_dtype="float32"))
    runs = tmp_path / "runs"
    args = reproduce.build_parser().parse_args(
        ["--runs-root", str(runs), "--out", str(tmp_path / "out"), "--seeds", "0-1",
         "--episodes", "30", "--env-map", "u_maze=point_u_maze"])
    args.env_map = {"u_maze": "point_u_maze"}
    exp = reproduce.Exp("u_maze", "dsc", 30, "0-1")

    def group(name, seeds, finished=True):
        g = runs / name
        g.mkdir(parents=True)
        (g / "group.json").write_text(json.dumps({"seeds": seeds, "config": cfg}))
        for s in seeds:
            log = RunLogger(str(g / f"s{s}"))
            for j in (1, 2, 3):
                log.log({"iteration": j, "env_steps": 100 * j, "episodes": 10 * j})
            log.close()
            if finished:
                (g / f"s{s}" / "eval.json").write_text(json.dumps({"iteration": 3}))
        return str(g)

    assert reproduce.group_dir(exp, args) == str(runs / "point_u_maze-dsc-g0-1")   # nothing yet
    group("point_u_maze-dsc-g2-5", [2, 3, 4, 5])            # does not hold seeds 0-1
    group("point_u_maze-dsc-g0-3-long", [0, 1, 2, 3])        # another tag
    group("point_u_maze-dsc-dp-g0-3", [0, 1, 2, 3])          # another subgoal rule
    big = group("point_u_maze-dsc-g0-3", [0, 1, 2, 3])
    group("point_u_maze-dsc-g0-9", list(range(10)))          # larger still: the smaller wins
    assert reproduce.group_dir(exp, args) == big
    data = reproduce.Data(args, {"6": [exp]})
    assert [os.path.basename(d) for d in data.dirs(exp)] == ["s0", "s1"]
    assert data.finished(exp)
    assert data.info[exp]["name"] == "`point_u_maze-dsc-g0-3` (seeds 0-1 of it)"
    args.dry_run = True
    assert reproduce.train_one(exp, args, None) == "skipped"
    assert "point_u_maze-dsc-g0-3: skipped (finished)" in capsys.readouterr().out
    # a group of the asked seeds' own name comes first
    own = group("point_u_maze-dsc-g0-1", [0, 1])
    assert reproduce.group_dir(exp, args) == own
    assert reproduce.Data(args, {"6": [exp]}).info[exp]["name"] == "`point_u_maze-dsc-g0-1`"
    # a larger group without a checkpoint or final evaluations (stale) is not resumed for them
    shutil.rmtree(own)
    shutil.rmtree(big)
    shutil.rmtree(runs / "point_u_maze-dsc-g0-9")
    group("point_u_maze-dsc-g0-3", [0, 1, 2, 3], finished=False)
    assert reproduce.train_one(exp, args, None) == "dry-run"
    out = capsys.readouterr().out
    assert "point_u_maze-dsc-g0-1: would start" in out and "--seeds 0-1" in out


def test_training_time_sums_each_groups_last_wall_clock_per_figure(tmp_path):
    """The README's training-time table: a group's time is the largest `wall_clock` of its seeds'
    last rows; a figure sums its groups; the total counts a group two figures share once."""
    from dscpp_jax.config import preset
    from dscpp_jax.run_logging import RunLogger
    runs = tmp_path / "runs"
    args = reproduce.build_parser().parse_args(
        ["--runs-root", str(runs), "--out", str(tmp_path / "out"), "--seeds", "0-1",
         "--episodes", "30", "--env-map", "u_maze=point_u_maze"])
    args.env_map = {"u_maze": "point_u_maze"}

    def group(algo, walls):
        cfg = _flat(preset("fast", "point_u_maze", algo, td3_dtype="float32"))
        g = runs / f"point_u_maze-{algo}-g0-1"
        g.mkdir(parents=True)
        (g / "group.json").write_text(json.dumps({"seeds": [0, 1], "config": cfg}))
        for s, last in enumerate(walls):
            log = RunLogger(str(g / f"s{s}"))
            for j, w in enumerate((1.0, last), 1):
                log.log({"iteration": j, "env_steps": 100 * j, "episodes": 10 * j,
                         "wall_clock": w})
            log.close()

    group("dsc", [3600.0, 3000.0])
    group("mf_dscpp", [1800.0, 1800.0])
    dsc, mf = (reproduce.Exp("u_maze", a, 30, "0-1") for a in ("dsc", "mf_dscpp"))
    untrained = reproduce.Exp("u_maze", "dual", 30, "0-1")
    data = reproduce.Data(args, {"5": [dsc, mf, untrained], "A3": [dsc]})
    assert reproduce.group_wall(data, dsc) == 3600.0
    assert reproduce.group_wall(data, untrained) is None
    lines = reproduce.training_time_lines(data)
    assert "| 5 | 2 | 1.50 |" in lines
    assert "| A3 | 1 | 1.00 |" in lines
    assert lines[-1] == "| all (each group once) | 2 | 1.50 |"
    assert not any(line.startswith("| 6 ") for line in lines)   # no runs: no row

"""experiments/time_to_threshold.py: the first full in-band window at or above the threshold."""
import csv
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "experiments"))
import time_to_threshold as ttt  # noqa: E402

sys.path.pop(0)


def _metrics(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, ["iteration", "episodes", "wall_clock", "inband/window",
                               "inband/success_rate"])
        w.writeheader()
        for r in rows:
            w.writerow(dict(zip(w.fieldnames, r)))


def test_first_hit_needs_a_full_window_at_the_threshold(tmp_path):
    p = str(tmp_path / "metrics.csv")
    _metrics(p, [(1, 0, 5.0, 0, 0.0),
                 (2, 10, 6.5, 3, 1.0),       # above, but the window is not full yet
                 (3, 20, 8.0, 4, 0.75),      # full, below
                 (4, 30, 9.5, 4, 0.8),       # the first hit
                 (5, 40, 11.0, 4, 1.0)])
    hit = ttt.first_hit(p, 0.8, window=4)
    assert hit == dict(iteration=4, episodes=30, loop_s=9.5, success=0.8)
    assert ttt.first_hit(p, 1.01, window=4) is None
    assert ttt.first_hit(str(tmp_path / "missing.csv"), 0.8, window=4) is None


def test_inband_window_follows_the_config(tmp_path):
    d = tmp_path / "run"
    assert ttt.inband_window(str(d)) is None
    d.mkdir()
    (d / "config.json").write_text(json.dumps(
        {"config": {"inband_eval_envs": 32, "inband_eval_window": 0}}))
    assert ttt.inband_window(str(d)) == 32
    (d / "config.json").write_text(json.dumps(
        {"config": {"inband_eval_envs": 32, "inband_eval_window": 64}}))
    assert ttt.inband_window(str(d)) == 64


def test_profile_startup_times_every_phase_up_to_the_one_asked(tmp_path):
    """experiments/profile_startup.py on the point twin: each phase up to --until timed, the JSON
    written, and with --cprofile one stats file per phase after the imports."""
    import pstats
    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    import profile_startup
    sys.path.pop(0)
    out, prof = str(tmp_path / "p.json"), str(tmp_path / "prof")
    res = profile_startup.main(["--env", "point_u_maze", "--algo", "td3_her", "--until", "lower",
                                "--set", "num_envs=2", "--cprofile", prof, "--out", out])
    phases = list(res["phases_s"])
    assert phases == ["interpreter to script", "imports", "accelerator start (jax.devices)",
                      "env build", "init: compile or cache load (ahead)", "train_step: trace",
                      "train_step: lower"]
    assert all(v >= 0 for v in res["phases_s"].values())
    assert json.load(open(out))["phases_s"] == res["phases_s"]
    assert sorted(os.listdir(prof)) == ["accelerator_start.prof", "env_build.prof",
                                        "init__compile_or_cache_load.prof",
                                        "train_step__lower.prof", "train_step__trace.prof"]
    pstats.Stats(os.path.join(prof, "init__compile_or_cache_load.prof"))   # readable


def test_iteration_times_split_the_warm_up_from_the_rest(tmp_path):
    p = str(tmp_path / "metrics.csv")
    with open(p, "w", newline="") as f:
        w = csv.DictWriter(f, ["iteration", "wall_clock", "train/warmup"])
        w.writeheader()
        for it, wall, warm in [(1, 30.0, 1), (2, 31.0, 1), (3, 32.2, 1), (4, 33.5, 0),
                               (5, 35.0, 0), (6, 36.4, 0)]:
            w.writerow({"iteration": it, "wall_clock": wall, "train/warmup": warm})
    # warm-up steps 1.0 and 1.2 s; after it 1.3, 1.5, 1.4 s (the row's own flag decides)
    assert ttt.iteration_times(p) == dict(first_s=30.0, warmup_s=1.1, after_s=1.4)
    assert ttt.iteration_times(str(tmp_path / "none.csv")) == dict(first_s=None, warmup_s=None,
                                                                     after_s=None)


def test_seeds_run_one_after_another_and_the_summary_counts_the_goal(tmp_path, monkeypatch):
    calls = []

    def fake_time_one(dest, name, train_args, threshold, limit):
        calls.append((name, list(train_args)))
        seed = int(train_args[-1])
        hit = None if seed == 2 else dict(iteration=60 + seed, episodes=900 + seed,
                                          loop_s=90.0 + 20 * seed, success=0.94,
                                          command_s=100.0 + 20 * seed)
        return dict(name=name, hit=hit, stopped_s=200.0,
                    stopped_by="threshold" if hit else "limit")

    monkeypatch.setattr(ttt, "time_one", fake_time_one)
    dest = str(tmp_path / "d")
    res = ttt.main(["--dest", dest, "--name", "u", "--seeds", "0-1,2", "--goal", "120",
                    "--", "--env", "u_maze"])
    assert calls == [(f"u_s{s}", ["--env", "u_maze", "--seed", str(s)]) for s in (0, 1, 2)]
    assert [r["name"] for r in res] == ["u_s0", "u_s1", "u_s2"]
    md = open(os.path.join(dest, "summary_u.md")).read()
    assert "| u_s1 | - s | - s | - / - | 61, 901 | 120 s |" in md
    assert "not reached within the limit (200.0 s) |" in md
    assert "2 of 3 runs reached the threshold; command start to threshold 100-120 s, median 110 s; " \
           "within 120 s: 2 of 3" in md
    summary = json.load(open(os.path.join(dest, "summary_u.json")))
    assert summary["goal_s"] == 120 and len(summary["runs"]) == 3


def test_the_summary_shows_the_start_up_that_train_recorded(tmp_path):
    run = tmp_path / "u_s0"
    run.mkdir()
    assert ttt.startup_of(str(run)) is None
    (run / "startup.jsonl").write_text(
        json.dumps({"command_to_first_iteration_s": 53.8, "phases_s": {"first iteration": 1.1}})
        + "\n" + json.dumps({"command_to_first_iteration_s": 20.0, "phases_s": {}}) + "\n")
    st = ttt.startup_of(str(run))
    assert st["command_to_first_iteration_s"] == 53.8
    row = dict(name="u_s0", startup=st, times=dict(first_s=1.1, warmup_s=1.02, after_s=1.2),
               hit=dict(iteration=72, episodes=912, command_s=141.1))
    assert "| u_s0 | 53.8 s | 1.1 s | 1.02 / 1.20 | 72, 912 | 141 s |" in ttt.summary_table([row])
    (run / "startup.jsonl").write_text("{")   # cut short
    assert ttt.startup_of(str(run)) is None


def test_seeds_refuse_a_seed_in_the_train_arguments(tmp_path):
    import pytest
    with pytest.raises(SystemExit):
        ttt.main(["--dest", str(tmp_path), "--name", "u", "--seeds", "0-1", "--", "--seed", "3"])
    with pytest.raises(SystemExit):
        ttt.main(["--dest", str(tmp_path), "--name", "u", "--seeds", "3-1", "--", "--env", "u_maze"])


def test_a_run_that_ends_short_of_the_threshold_says_where_it_got_to(tmp_path):
    run = tmp_path / "f_s0"
    run.mkdir()
    assert ttt.run_end(str(run)) is None
    _metrics(run / "metrics.csv", [(1, 10, 1.0, 32, 0.0), (201, 2010, 290.0, 32, 0.5)])
    assert ttt.run_end(str(run)) == dict(iteration=201, episodes=2010, final_success=None)
    (run / "eval.json").write_text(json.dumps({"eval/success_rate": 0.93}))
    end = ttt.run_end(str(run))
    assert end == dict(iteration=201, episodes=2010, final_success=0.93)
    rows = [dict(name="f_s0", hit=None, stopped_by="exit 0", stopped_s=315.4, end=end),
            dict(name="f_s1", hit=None, stopped_by="exit 1", stopped_s=12.0, end=None),
            dict(name="f_s2", hit=None, stopped_by="limit", stopped_s=420.0,
                 end=dict(iteration=300, episodes=1800, final_success=None))]
    md = ttt.summary_table(rows, goal=360)
    assert ("not reached: the run ended at iteration 201, 2,010 episodes, final success 0.93 "
            "(315.4 s) | - | - |") in md
    assert "not reached (stopped by exit 1 at 12.0 s) | - | - |" in md
    assert "not reached within the limit (420.0 s) at iteration 300, 1,800 episodes | - | - |" in md
    assert "0 of 3 runs reached the threshold; within 360 s: 0 of 3" in md


def test_row_s_reads_the_hit_on_the_runs_own_clock():
    """The timer polls once a second; row_s puts the hit where the run wrote it: its loop's start
    (start-up record: command to the first iteration's end, less that iteration) plus the row's
    wall-clock."""
    st = {"command_to_first_iteration_s": 29.45, "phases_s": {"first iteration": 0.986}}
    row = dict(name="u_s17", startup=st, times={},
               hit=dict(iteration=98, episodes=1223, loop_s=90.9839, command_s=120.1))
    assert ttt.loop_start_s(st) == 29.45 - 0.986
    assert ttt.row_s(row) == 119.4
    row["hit"]["row_s"] = ttt.row_s(row)
    assert "| 98, 1,223 | 120 s | 119.4 s |" in ttt.summary_table([row])
    assert ttt.row_s(dict(row, startup=None)) is None
    assert ttt.row_s(dict(row, startup={"command_to_first_iteration_s": 3.0})) is None
    assert ttt.row_s(dict(row, hit=None)) is None


def test_plot_draws_the_series_from_their_summaries(tmp_path):
    """plot_time_to_threshold.py: curves on the command's clock (full windows only), the hit on the
    run's clock, runs that compiled told apart from warm ones, and a PNG written."""
    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    import plot_time_to_threshold as ptt
    sys.path.pop(0)
    dest = tmp_path / "d"
    dest.mkdir()
    runs = []
    for name, compile_s, hit in (("u_s0", 60.0, True), ("u_s1", 9.0, True), ("u_s2", 9.5, False)):
        (dest / name).mkdir()
        _metrics(str(dest / name / "metrics.csv"),
                 [(1, 0, 1.0, 0, 0.0), (2, 10, 2.0, 4, 0.5), (3, 20, 3.0, 4, 0.9 if hit else 0.5)])
        st = {"command_to_first_iteration_s": compile_s + 11.0,
              "phases_s": {"first iteration": 1.0, ptt.COMPILE_PHASE: compile_s}}
        runs.append(dict(name=name, threshold=0.9, window=4, startup=st, stopped_s=30.0,
                         hit=dict(iteration=3, episodes=20, loop_s=3.0, command_s=compile_s + 14.0)
                         if hit else None))
    (dest / "summary_u.json").write_text(json.dumps(dict(threshold=0.9, goal_s=120, runs=runs)))
    out = str(tmp_path / "fig" / "t.png")
    got = ptt.main([str(dest / "summary_u.json"), "--goal", "120", "--goal", "180", "--out", out])
    assert os.path.getsize(out) > 0
    by = {r["name"]: r for r in got}
    assert by["u_s0"]["compiled"] and not by["u_s1"]["compiled"]
    assert by["u_s0"]["curve"] == ([70.0 + 2.0, 70.0 + 3.0], [0.5, 0.9])   # loop start 70 s
    assert by["u_s1"]["hit_s"] == 22.0 and by["u_s2"]["hit_s"] is None
    assert by["u_s2"]["stopped_s"] == 30.0   # drawn as an outline up to where it stopped
    assert ptt.short_names(["u_maze_s3", "u_maze_cold_s3"]) == ["s3", "cold_s3"]

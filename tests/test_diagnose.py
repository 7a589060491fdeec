"""diagnose: each way a chain fails from the start, read off hand-written metrics.csv / eval.json."""
import csv
import json
import math
import os

import pytest

from dscpp_jax import cli
from dscpp_jax import config as C
from dscpp_jax import diagnose as D


def _run(tmp_path, name, last, ev, episodes=100):
    d = tmp_path / name
    d.mkdir()
    row = {"iteration": 5, "options/start_covered": 0, "options/capacity_hit": 0,
           "options/num_options": 10, "options/gestation_executions": 0,
           "options/gestation_successes": 0, "options/gestation_parent": -1, **last}
    with open(d / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        w.writeheader()
        w.writerow({**row, "iteration": 4, "options/start_covered": 1})   # only the last row counts
        w.writerow(row)
    with open(d / "eval.json", "w") as f:
        json.dump({"eval/flipped_failures": 0.0, **ev}, f)
    with open(d / "config.json", "w") as f:
        json.dump({"config": {"eval_episodes": episodes}}, f)
    return str(d)


def test_a_link_in_gestation_says_where_it_was_tried_from(tmp_path):
    """Runs that log the link's start distances get them in the verdict; blank cells (nothing
    in gestation, or no failure stored yet) leave the verdict as before."""
    slow = {"options/gestation_executions": 900, "options/gestation_successes": 3,
            "options/gestation_parent": 7}
    r = D.diagnose_run(_run(tmp_path, "slow", {**slow, "options/gestation_fail_distance": 6.25,
                                               "options/gestation_success_distance": 2.04},
                            {"eval/success_rate": 0.0}))
    assert r["verdict"] == ("not covered (link in gestation towards option 7: 900 executions, "
                            "3 successes; failures started 6.2 from its target (successes 2.0))")
    stalled = {"options/gestation_executions": 1500, "options/gestation_parent": 4,
               "options/gestation_fail_distance": 9.0, "options/gestation_success_distance": ""}
    r = D.diagnose_run(_run(tmp_path, "stalled", stalled, {"eval/success_rate": 0.0}))
    assert r["verdict"] == ("stalled link (targets option 4, 1500 executions; failures started "
                            "9.0 from its target)")
    assert D.verdict_kind(r["verdict"]) == "stalled link"
    r = D.diagnose_run(_run(tmp_path, "blank", {**slow, "options/gestation_fail_distance": "",
                                                "options/gestation_success_distance": ""},
                            {"eval/success_rate": 0.0}))
    assert r["verdict"] == ("not covered (link in gestation towards option 7: 900 executions, "
                            "3 successes)")


def test_each_failure_gets_its_verdict(tmp_path):
    cases = {
        "solved": ({"options/start_covered": 1}, {"eval/success_rate": 0.9}, "solved"),
        "falls": ({"options/start_covered": 1},
                  {"eval/success_rate": 0.6, "eval/flipped_failures": 30.0}, "falls"),
        "weak": ({"options/start_covered": 1},
                 {"eval/success_rate": 0.1, "eval/flipped_failures": 5.0,
                  "eval/option_success/0": 0.0, "eval/option_success/3": 0.9,
                  "eval/option_success/7": 0.05, "eval/option_success/8": math.nan},
                 "weak link 7"),
        "full": ({"options/capacity_hit": 1, "options/num_options": 24},
                 {"eval/success_rate": 0.0}, "table full"),
        "stalled": ({"options/gestation_executions": 1200, "options/gestation_parent": 15},
                    {"eval/success_rate": 0.0}, "stalled link (targets option 15, 1200 executions)"),
        "slow": ({"options/gestation_executions": 1200, "options/gestation_successes": 2,
                  "options/gestation_parent": 12},
                 {"eval/success_rate": 0.0},
                 "not covered (link in gestation towards option 12: 1200 executions, 2 successes)"),
        "growing": ({"options/gestation_executions": 40, "options/gestation_successes": 1,
                     "options/gestation_parent": 9},
                    {"eval/success_rate": 0.0},
                    "not covered (link in gestation towards option 9: 40 executions, 1 success)"),
        # the in-band window still saw the chain work; the final evaluation did not
        "late": ({"options/start_covered": 1, "inband/success_rate": 0.97},
                 {"eval/success_rate": 0.0, "eval/option_success/23": 0.0},
                 "broke late (weak link 23)"),
        "late_but_solved": ({"options/start_covered": 1, "inband/success_rate": 0.97},
                            {"eval/success_rate": 0.85}, "solved"),
        "small_drop": ({"options/start_covered": 1, "inband/success_rate": 0.91},
                       {"eval/success_rate": 0.79}, "start covered, failing on the way"),
        "inband_low": ({"options/start_covered": 1, "inband/success_rate": 0.5},
                       {"eval/success_rate": 0.6, "eval/flipped_failures": 30.0}, "falls"),
    }
    for name, (last, ev, verdict) in cases.items():
        r = D.diagnose_run(_run(tmp_path, name, last, ev))
        assert r["verdict"] == verdict, name
    falls = D.diagnose_run(str(tmp_path / "falls"))
    assert falls["falls"] == 30 and falls["failures"] == 40 and falls["start_covered"]
    assert D.diagnose_run(str(tmp_path / "weak"))["weak_links"] == [7]   # not the global option
    table = D.format_table([D.diagnose_run(str(tmp_path / n)) for n in cases], str(tmp_path))
    # the first row had the start covered, the last not: one loss, no link since
    assert "| full | 0.00 | - | - | - | no | 1 | 24 (full) | 0 of 100 | - | - | table full |" in table
    assert "| falls | 0.60 | - | - | - | yes | 0 | 10 | 30 of 40 | - | - | falls |" in table
    assert ("| late | 0.00 | 0.97 | 0.97 | - | yes | 0 | 10 | 0 of 100 | 23 | - | "
            "broke late (weak link 23) |") in table
    # the summary counts kinds, details left out: "weak link 7" and "weak link 23" are one kind
    assert D.verdict_kind("stalled link (targets option 15, 1200 executions)") == "stalled link"
    assert D.verdict_kind("falls; weak links 3, 4") == "falls and weak link"
    assert D.verdict_kind("not covered (link in gestation towards option 12: 1200 executions, "
                          "2 successes)") == "not covered"
    summary = D.format_summary([D.diagnose_run(str(tmp_path / n)) for n in cases])
    assert summary == ("11 runs: 2 falls; 2 not covered; 2 solved; 1 broke late; "
                       "1 stalled link; 1 start covered, failing on the way; 1 table full; "
                       "1 weak link")
    # mean ± s.e. over the runs, worked by hand: (1, 0.5, 0) -> 0.50 ± sqrt(0.25 / 3);
    # in-band (0.9, none, 0.7) -> 0.80 ± 0.10 over the two runs that have it
    nan = float("nan")
    rows = [dict(success=1.0, inband=0.9), dict(success=0.5, inband=nan),
            dict(success=0.0, inband=0.7)]
    assert D.format_means(rows) == ("success from the start 0.50 ± 0.29, "
                                    "in-band at the end 0.80 ± 0.10 (2 of 3 runs)")
    assert D.format_means([]) == "success from the start -, in-band at the end -"


def test_a_chain_that_reached_solved_in_band_and_lost_it_decayed(tmp_path):
    """The in-band window once at 0.8 or more, at the end and in the final evaluation below:
    "decayed"; a peak below 0.8, or a last window still there (broke late), is not."""
    def run(name, inband, success):
        d = tmp_path / name
        d.mkdir()
        with open(d / "metrics.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=["iteration", "options/start_covered",
                                              "options/num_options", "inband/success_rate"])
            w.writeheader()
            for i, v in enumerate(inband):
                w.writerow({"iteration": i, "options/start_covered": 1,
                            "options/num_options": 16, "inband/success_rate": v})
        with open(d / "eval.json", "w") as f:
            json.dump({"eval/success_rate": success, "eval/flipped_failures": 0.0,
                       "eval/option_success/12": 0.1}, f)
        return D.diagnose_run(str(d))
    r = run("decayed", ["", 0.3, 0.91, 0.66, 0.12], 0.07)
    assert r["verdict"] == "decayed (weak link 12)" and r["best_inband"] == 0.91
    assert D.verdict_kind(r["verdict"]) == "decayed"
    assert "| 0.07 | 0.12 | 0.91 | - | yes |" in D.format_table([r])
    assert run("never", [0.3, 0.5, 0.1], 0.01)["verdict"] == "weak link 12"
    assert run("late", [0.3, 0.91, 0.9], 0.05)["verdict"] == "broke late (weak link 12)"
    assert run("solved", [0.91, 0.5], 0.85)["verdict"] == "solved"


def test_coverage_lost_counts_the_start_leaving_the_chain_after_it_was_first_covered(tmp_path):
    """Losses count 1 -> 0 changes from the first covered row on (rows before it and rows
    without the column do not count); links are the options made from that row to the last."""
    d = _run(tmp_path, "flapping", {"options/start_covered": 1}, {"eval/success_rate": 0.0})
    covered = [0, 0, 1, 1, 0, "", 0, 1, 0, 1, 1, 0, 1]
    options = [2, 3, 9, 9, 10, 10, 10, 10, 11, 11, 11, 12, 12]
    with open(f"{d}/metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["iteration", "options/start_covered", "options/num_options"])
        for i, (c, n) in enumerate(zip(covered, options)):
            w.writerow([i + 1, c, n])
    # losses at rows 5, 9 and 12 (the blank row 6 is skipped); options 9 -> 12
    assert D.coverage_lost(f"{d}/metrics.csv") == (3, 3)
    r = D.diagnose_run(d)
    assert r["coverage_lost"] == (3, 3)
    assert "| flapping | 0.00 | - | - | - | yes | 3 (+3 links) | 12 |" in D.format_table([r], str(tmp_path))
    with open(f"{d}/metrics.csv", "w") as f:
        f.write("iteration,options/start_covered,options/num_options\n1,0,2\n2,1,5\n3,1,6\n")
    assert D.coverage_lost(f"{d}/metrics.csv") == (0, 1)
    assert "| yes | 0 (+1 link) | 6 |" in D.format_table([D.diagnose_run(d)], str(tmp_path))
    with open(f"{d}/metrics.csv", "w") as f:
        f.write("iteration,options/start_covered,options/num_options\n1,0,2\n2,0,5\n")
    assert D.coverage_lost(f"{d}/metrics.csv") is None


def test_dips_count_periodic_evaluations_below_half_once_solved(tmp_path):
    d = _run(tmp_path, "dipping", {"options/start_covered": 1}, {"eval/success_rate": 0.9})
    rows = [0.0, "", 0.0, 0.86, 0.69, "", 0.0, 0.28, 0.93, 0.41, 0.9]
    with open(f"{d}/metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["iteration", "eval/success_rate", "options/start_covered"])
        for i, v in enumerate(rows):
            w.writerow([i + 1, v, 1])
    assert D.dips(f"{d}/metrics.csv") == (3, 7)   # 0.0, 0.28, 0.41 of the seven from 0.86 on
    r = D.diagnose_run(d)
    assert r["dips"] == (3, 7) and r["verdict"] == "solved"
    assert "| dipping | 0.90 | - | - | 3 of 7 | yes | 0 |" in D.format_table([r], str(tmp_path))
    never = _run(tmp_path, "never", {}, {"eval/success_rate": 0.0})
    with open(f"{never}/metrics.csv", "w") as f:
        f.write("iteration,eval/success_rate,options/start_covered\n1,0.0,0\n2,0.5,0\n")
    assert D.dips(f"{never}/metrics.csv") == (0, 0)
    assert "| never | 0.00 | - | - | - | no | - |" in D.format_table([D.diagnose_run(never)], str(tmp_path))


def test_diagnose_takes_groups_and_says_what_is_missing(tmp_path, capsys):
    a = _run(tmp_path, "a", {"options/start_covered": 1}, {"eval/success_rate": 1.0})
    with pytest.raises(ValueError, match="no metrics.csv"):
        D.diagnose_run(str(tmp_path))
    # a run stopped before its final evaluation: read off metrics.csv, left out of the mean
    (tmp_path / "a" / "eval.json").rename(tmp_path / "eval.json.bak")
    r = D.diagnose_run(a)
    assert r["verdict"] == "unfinished (0 episodes, start covered, no final evaluation)"
    assert math.isnan(r["success"]) and D.verdict_kind(r["verdict"]) == "unfinished"
    assert "| a | - | - | - | - | yes | 0 |" in D.format_table([r], str(tmp_path))
    done = _run(tmp_path, "done", {"options/start_covered": 1}, {"eval/success_rate": 0.5})
    assert D.format_summary([r, D.diagnose_run(done)]) == "2 runs: 1 start covered, failing on the way; 1 unfinished"
    assert D.format_means([r, D.diagnose_run(done)]).startswith(
        "success from the start 0.50 ± 0.00 (1 of 2 runs)")
    # train's own end-of-run line gives no verdict for a run whose evaluation is missing
    cfg = C.preset("fast", env="point_u_maze", algo="mb_dscpp")
    assert D.chain_verdict(cfg, a) is None
    assert D.chain_verdict(cfg, done) == "start covered, failing on the way"
    (tmp_path / "eval.json.bak").rename(tmp_path / "a" / "eval.json")
    flat = _run(tmp_path, "flat", {}, {"eval/success_rate": 0.0})
    with open(f"{flat}/metrics.csv", "w") as f:
        f.write("iteration,train/episode_success\n1,0.0\n")
    with pytest.raises(ValueError, match="options/"):
        D.diagnose_run(flat)
    # a group directory stands for its seeds
    (tmp_path / "g").mkdir()
    monkey = pytest.MonkeyPatch()
    monkey.setattr(D, "is_group_dir", lambda d: d == str(tmp_path / "g"))
    monkey.setattr(D, "seed_dirs", lambda d: [a, a])
    try:
        assert [r["run"] for r in D.diagnose([str(tmp_path / "g"), a])] == [a, a, a]
        assert cli.main(["diagnose", a]) == 0
    finally:
        monkey.undo()
    assert "| solved |" in capsys.readouterr().out


def _options_csv(path, links):
    """options.csv of `links`: {option: [(iteration, status, executions, successes), ...]}."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["iteration", "env_steps", "option", "status", "parent", "executions",
                    "successes", "positives", "negatives"])
        for k, snaps in links.items():
            for it, status, e, s in snaps:
                w.writerow([it, it * 100, k, status, k - 1, e, s, s, e - s])


def test_fading_links_are_mature_links_whose_last_span_lost_success(tmp_path):
    """Spans of FADE_SPAN executions from maturity on; a link fades when its best span was at
    least FADE_BEST and its last is FADE_DROP lower. Rows in gestation, the global option and a
    row's previous link (its counters restart) do not count."""
    def steady(rates, start=5, e0=0, per=20):
        out, e, s = [], e0, e0
        for i, r in enumerate(rates):
            out.append((start + 5 * i, "mature", e, s))
            e, s = e + per, s + round(per * r)
        return out + [(start + 5 * len(rates), "mature", e, s)]
    links = {
        0: steady([0.0] * 6),                                  # the global option: ignored
        2: [(0, "gestation", 0, 0)] + steady([1.0, 1.0, 0.9, 0.9, 0.2, 0.2]),   # fades
        3: steady([0.9] * 6),                                  # steady
        4: steady([1.0] * 4) + steady([0.5, 0.5, 0.5, 0.5], start=30),   # reused row
        5: steady([1.0, 1.0, 0.6, 0.6]),                       # a drop of 0.4: fades
        6: steady([1.0, 1.0, 0.8, 0.8]),                       # a drop of 0.2: does not
    }
    d = tmp_path / "run"
    d.mkdir()
    _options_csv(d / "options.csv", links)
    spans = D.link_spans(str(d / "options.csv"))
    assert 0 not in spans
    assert spans[2] == [(5, 15, 40, 1.0), (15, 25, 40, 0.9), (25, 35, 40, 0.2)]
    assert [r for *_, r in spans[4]] == [0.5, 0.5]              # only the new link's spans
    assert D.fading_links(str(d)) == [(2, 1.0, 0.2), (5, 1.0, 0.6)]
    assert D.fading_links(str(tmp_path)) is None               # no options.csv: no reading


def test_the_table_names_fading_links(tmp_path):
    run = _run(tmp_path, "decayed", {"options/start_covered": 1}, {"eval/success_rate": 0.1})
    _options_csv(os.path.join(run, "options.csv"),
                 {7: [(5, "mature", 0, 0), (10, "mature", 50, 45), (15, "mature", 100, 55)]})
    r = D.diagnose_run(run)
    assert r["fading_links"] == [(7, 0.9, 0.2)]
    assert "| 7 (0.90 to 0.20) |" in D.format_table([r])
    old = _run(tmp_path, "old", {"options/start_covered": 1}, {"eval/success_rate": 0.9})
    assert D.diagnose_run(old)["fading_links"] is None
    assert D.format_table([D.diagnose_run(old)]).splitlines()[-1].endswith("| - | - | solved |")

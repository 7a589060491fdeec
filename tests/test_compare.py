"""compare: settings side by side, read off hand-written metrics.csv / eval.json / group.json."""
import csv
import json
import math

import pytest

from dscpp_jax import cli
from dscpp_jax import compare as C

COLS = ["iteration", "episodes", "wall_clock", "inband/success_rate", "options/num_mature",
        "options/num_options", "options/start_covered", "time/iteration_s", "train/warmup"]


def _run(d, rows, ev=None, eval_episodes=100):
    """A run directory: rows are tuples in COLS order (None: a blank cell)."""
    d.mkdir(parents=True)
    with open(d / "metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLS)
        for r in rows:
            w.writerow(["" if v is None else v for v in r])
    if ev is not None:
        (d / "eval.json").write_text(json.dumps(ev))
    (d / "config.json").write_text(json.dumps({"config": {"eval_episodes": eval_episodes}}))
    return str(d)


def _group(d, seeds, runs):
    """A seed-group directory whose seed directories s<seed> hold `runs` (lists of rows, evals)."""
    d.mkdir(parents=True)
    (d / "group.json").write_text(json.dumps({"seeds": seeds}))
    for s, (rows, ev) in zip(seeds, runs):
        _run(d / f"s{s}", rows, ev)
    return str(d)


# it, episodes, wall, in-band, mature, options, covered, s/it, warm-up
FAST = [(1, 0, 10, None, 0, 2, 0, 9.0, 1), (2, 0, 11, 0.0, 1, 3, 0, 1.0, 1),
        (3, 40, 13, 0.2, 3, 5, 1, 2.0, 0), (4, 90, 15, 0.95, 3, 5, 0, 2.0, 0),
        (5, 150, 17, 0.9, 5, 6, 1, 4.0, 0), (6, 220, 19, 1.0, 5, 6, 1, 4.0, 0)]
SLOW = [(1, 0, 10, None, 0, 2, 0, 9.0, 1), (2, 0, 11, 0.0, 1, 3, 0, 1.0, 1),
        (3, 30, 13, 0.0, 1, 3, 0, 2.0, 0), (4, 60, 15, 0.5, 3, 4, 1, 2.0, 0)]


def test_run_numbers(tmp_path):
    r = C.read_run(_run(tmp_path / "a", FAST, {"eval/success_rate": 0.9,
                                               "eval/flipped_failures": 7.0}),
                   levels=(0.1, 0.9), mature=(1, 5, 9))
    assert r["success"] == 0.9 and r["falls"] == 7.0 and r["failures"] == 10
    assert r["inband_first"] == {"0.1": (3, 40.0), "0.9": (4, 90.0)}
    assert r["mature_first"] == {"1": (2, 0.0), "5": (5, 150.0), "9": None}
    assert r["covered_from"] == 150.0       # covered at iteration 3, lost at 4, for good from 5
    assert r["options_end"] == 6
    assert r["s_per_iteration"] == 3.0      # median of 2, 2, 4, 4 (the warm-up's left out)
    s = C.read_run(_run(tmp_path / "b", SLOW), levels=(0.9,), mature=(1,))
    assert math.isnan(s["success"]) and s["failures"] is None and s["falls"] is None
    assert s["inband_first"] == {"0.9": None} and s["covered_from"] == 60.0


def test_labels_pool_groups_and_the_table_says_it(tmp_path):
    ev = lambda x, f: {"eval/success_rate": x, "eval/flipped_failures": f}
    g1 = _group(tmp_path / "g1", [0, 1], [(FAST, ev(0.9, 6.0)), (SLOW, ev(0.5, 10.0))])
    g2 = _group(tmp_path / "g2", [2], [(FAST, ev(1.0, 0.0))])
    other = _run(tmp_path / "other", SLOW, ev(0.7, 1.0))
    res = C.compare([f"A={g1}", f"A={g2}", other], levels=(0.1, 0.9), mature=(3,))
    assert list(res) == ["A", "other"]
    a = res["A"]["summary"]
    assert a["runs"] == 3 and a["finished"] == 3 and a["solved"] == 2
    assert a["success_mean"] == pytest.approx(0.8)
    assert a["success_se"] == pytest.approx(math.sqrt(0.07) / math.sqrt(3))
    assert a["inband_first"]["0.9"] == {"reached": 2, "iterations": [4, 4], "median": 4,
                                        "mean": 4}
    assert a["inband_first"]["0.1"]["iterations"] == [3, 4, 3]
    assert a["mature_first"]["3"] == {"reached": 3, "median": 3}
    assert a["covered"] == {"runs": 3, "median_episodes": 150.0}
    assert a["falls"] == [16, 10 + 50 + 0] and a["options_end"] == [4, 6]
    table = C.format_table(res)
    assert table.splitlines()[0] == "| | A | other |"
    assert "| final success from the start, mean ± s.e. | 0.80 ± 0.15 | 0.70 ± 0.00 |" in table
    assert "| in-band >= 0.9 first: runs, median (mean) iteration | 2 of 3, 4 (4.0) | 0 of 1 |" \
        in table
    path = tmp_path / "out" / "cmp.json"
    C.write_json(res, str(path))
    back = json.loads(path.read_text())
    assert back["A"]["summary"]["falls"] == [16, 60]
    assert back["A"]["runs"][1]["inband_first"]["0.9"] is None


def test_cli_compare_and_its_errors(tmp_path, capsys):
    run = _run(tmp_path / "r", FAST, {"eval/success_rate": 1.0})
    assert cli.main(["compare", f"x={run}", "--levels", "0.5", "--mature", "1",
                     "--json", str(tmp_path / "c.json")]) == 0
    out = capsys.readouterr().out
    assert "| in-band >= 0.5 first: runs, median (mean) iteration | 1 of 1, 4 (4.0) |" in out
    assert (tmp_path / "c.json").is_file()
    with pytest.raises(ValueError, match="not a run or group directory: .*nowhere"):
        C.compare([str(tmp_path / "nowhere")])
    with pytest.raises(ValueError, match="success levels lie in"):
        C.compare([run], levels=(1.5,))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no metrics.csv"):
        C.compare([str(tmp_path / "empty")])


def test_cli_output_cut_short_by_its_reader_is_no_error(tmp_path):
    """`compare ... | head -1`: the reader leaves early; no traceback, no 'error:' about the disk."""
    import subprocess
    import sys
    run = _run(tmp_path / "r", FAST, {"eval/success_rate": 1.0})
    reader = subprocess.Popen(["head", "-c", "1"], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    # many labels make the table longer than the pipe's buffer, so the writer meets the closed pipe
    labels = [f"x{i}={run}" for i in range(1500)]
    writer = subprocess.run([sys.executable, "-m", "dscpp_jax.cli", "compare", *labels],
                            stdout=reader.stdin, stderr=subprocess.PIPE, text=True, timeout=300)
    reader.stdin.close()
    assert reader.stdout.read() == b"|"
    reader.wait()
    assert writer.returncode == 141, writer.stderr
    assert "error" not in writer.stderr.lower() and "Traceback" not in writer.stderr


def test_training_time_on_the_back_is_averaged_after_the_warm_up(tmp_path):
    def run(name, shares):
        d = tmp_path / name
        d.mkdir()
        with open(d / "metrics.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["iteration", "episodes", "wall_clock", "train/warmup",
                        "train/on_back_share"])
            for i, (warm, v) in enumerate(shares):
                w.writerow([i + 1, 10 * i, i, warm, v])
        return str(d)
    a = run("a", [(1, 0.5), (0, 0.1), (0, 0.3)])         # the warm-up's 0.5 is left out
    b = run("b", [(0, 0.0), (0, 0.0)])
    assert C.read_run(a, (0.5,), (1,))["on_back_share"] == pytest.approx(0.2)
    assert C.read_run(_run(tmp_path / "old", SLOW), (0.5,), (1,))["on_back_share"] is None
    res = C.compare([f"X={a}", f"X={b}"], levels=(0.5,), mature=(1,))
    assert res["X"]["summary"]["on_back_share"] == pytest.approx([0.1, 0.0, 0.2])
    assert ("| training steps on the back after the warm-up: mean share (runs' range) "
            "| 10.0% (0.0%-20.0%) |") in C.format_table(res)

"""Smoke test of experiments/bench_replay_draws.py: both ways of drawing the dynamics model's
minibatches give the same trained model, and both are timed and recorded."""
import json

import pytest

from tests.experiment_scripts import load


def test_bench_replay_draws_checks_both_draws_agree(tmp_path):
    bench = load("bench_replay_draws")
    out = str(tmp_path / "b.json")
    assert bench.main(["--steps", "6", "--capacity", "3000", "--fill", "0.3", "--hidden", "16",
                       "--batch", "32", "--reps", "1", "--out", out]) == 0
    res = json.load(open(out))
    assert res["same_result"] is True
    assert res["positions_listed_once_s"] > 0 and res["searched_per_step_s"] > 0
    assert res["args"]["steps"] == 6
    with pytest.raises(SystemExit):
        bench.main(["--fill", "0"])

"""Smoke test of experiments/profile_train_step.py on a point maze (timings are not checked,
only that every part is timed and recorded)."""
import json

import pytest

from tests.experiment_scripts import load


def test_profile_times_learns_parts_on_a_trained_state(tmp_path):
    prof = load("profile_train_step")
    out = str(tmp_path / "p.json")
    assert prof.main(["--env", "point_u_maze", "--num-envs", "4", "--reps", "1", "--learn-parts",
                      "--trained", "1", "--chained", "2", "--compile-cache", str(tmp_path / "xla"), "--set", "steps_per_iter=10", "--out", out]) == 0
    res = json.load(open(out))
    (r,) = res["results"]
    assert r["trained_iterations"] == 1 and r["options"] >= 1
    assert set(r["learn_parts"]) == {"dyn_normaliser_s", "dyn_updates_s", "refit_s",
                                     "grow_chain_s", "chain_metrics_s", "finite_checks_s"}
    assert all(v > 0 for v in r["learn_parts"].values())
    assert r["learn_after_rollout_s"] > 0 and isinstance(r["dirty_rows_after_rollout"], int)
    assert res["overrides"]["steps_per_iter"] == 10
    assert res["compile_cache"] == str(tmp_path / "xla")
    assert len(r["chained_train_step_each_s"]) == 2 and r["chained_train_step_s"] > 0
    assert r["train_step_compile_s"] > 0 and r["train_step_lower_s"] > 0
    with pytest.raises(SystemExit):
        prof.main(["--trained", "-1"])

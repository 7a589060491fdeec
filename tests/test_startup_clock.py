"""`run_logging.StartupClock`: the phases of a command's start add up, records append as lines, and the
process's age comes from /proc where there is one."""
import os
import sys
import time

import pytest

from dscpp_jax import cli
from dscpp_jax.run_logging import STARTUP_FILE, StartupClock, process_age_s, read_startup


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_process_age_grows_with_the_process():
    a = process_age_s()
    time.sleep(0.05)
    b = process_age_s()
    assert a is not None and 0.0 < a <= b
    assert b - a < 5.0


def test_phases_add_up_and_records_append(tmp_path, monkeypatch):
    monkeypatch.setattr("dscpp_jax.run_logging.process_age_s", lambda: 2.0)
    clock = StartupClock()
    time.sleep(0.02)
    clock.mark("a")
    clock.mark("b")
    time.sleep(0.02)
    clock.mark("a")   # a phase marked twice adds up
    rec = clock.write(str(tmp_path), iteration=1)
    assert set(rec["phases_s"]) == {"a", "b"} and rec["phases_s"]["a"] >= 0.03
    assert rec["process_start_to_clock_s"] == 2.0
    assert rec["command_to_first_iteration_s"] == pytest.approx(
        2.0 + sum(rec["phases_s"].values()), abs=2e-3)
    assert "to the end of the first iteration" in clock.line() and "process start 2.0 s" in clock.line()
    StartupClock().write(str(tmp_path), iteration=7)
    assert [r["iteration"] for r in read_startup(str(tmp_path))] == [1, 7]
    # a line cut short (a crash mid-write) is skipped, and the next command appends after it
    with open(tmp_path / STARTUP_FILE, "a") as f:
        f.write('{"iteration": 8, "pha')
    StartupClock().write(str(tmp_path), iteration=9)   # on a line of its own
    assert [r["iteration"] for r in read_startup(str(tmp_path))] == [1, 7, 9]
    assert read_startup(str(tmp_path / "none")) == []
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]   # no temporary left


def test_a_call_from_python_does_not_count_the_process_start(tmp_path):
    rec = StartupClock(count_process=False).write(str(tmp_path))
    assert rec["process_start_to_clock_s"] is None
    assert rec["command_to_first_iteration_s"] == pytest.approx(sum(rec["phases_s"].values()))


def test_main_counts_the_process_start_only_as_the_command(monkeypatch):
    monkeypatch.setattr(cli, "FROM_COMMAND_LINE", True)
    assert cli.main(["train", "--env", "point_u_maze", "--seeds", "3-1"]) == 2
    assert cli.FROM_COMMAND_LINE is False   # a call with arguments is not the command line

"""Pieces of the host loop that single runs and seed groups share: the wall-clock budget, the
health check of an iteration's metrics, and whether the loop runs on the main thread (where it
may take over Ctrl-C)."""
from __future__ import annotations

import math
import threading
import time
from typing import Optional

from dscpp_jax.run_logging import process_age_s


class TrainingDiverged(RuntimeError):
    """Learning produced NaN/inf; the message names the component."""


class Budget:
    """A wall-clock budget of `seconds` for a training command, counted from the start of the
    process (`count_process`, as the command line does) or from its creation. The loop asks
    `no_room()` before each iteration: true once the time left would not hold one more iteration
    (as long as the last one, not counting the first, which compiles) and the final checkpoint
    (as long as the last one written here). `None` seconds: no budget."""

    def __init__(self, seconds: Optional[float], count_process: bool = False):
        self.seconds = seconds
        age = process_age_s() if count_process else None
        self.start = time.time() - (age or 0.0)
        self.iterations = 0
        self.step_s = 0.0
        self.save_s = 0.0
        self.reached = False

    @property
    def deadline(self) -> float:
        return math.inf if self.seconds is None else self.start + self.seconds

    def iteration_took(self, seconds: float) -> None:
        self.iterations += 1
        if self.iterations > 1:   # the first iteration compiles: no guide to the next one
            self.step_s = seconds

    def save_took(self, seconds: float) -> None:
        self.save_s = max(self.save_s, seconds)

    def no_room(self, now: Optional[float] = None) -> bool:
        """Whether the loop must stop now to end within the budget (never before an iteration
        has run in this process)."""
        if self.seconds is None or self.iterations == 0:
            return False
        now = time.time() if now is None else now
        self.reached = now + self.step_s + self.save_s >= self.deadline
        return self.reached

    def reached_text(self) -> str:
        return (f"time budget of {self.seconds:.0f}s reached (counted from the start of the "
                f"process): saving a checkpoint and stopping")


def nonfinite_parts(metrics: dict) -> Optional[str]:
    """The parts of the learner whose values are no longer finite in one iteration's metrics
    (the ``finite/*`` flags and the TD3 and dynamics losses), named for a message; None when all
    are finite."""
    bad = [k.split("/", 1)[1] for k, v in metrics.items()
           if k.startswith("finite/") and float(v) < 0.5]
    for k in ("td3/critic_loss", "td3/actor_loss", "dynamics/loss"):
        if k in metrics and not math.isfinite(float(metrics[k])):
            bad.append(k)
    if not bad:
        return None
    names = {"td3": "the TD3 actor/critic parameters", "dynamics": "the dynamics model parameters",
             "classifiers": "the initiation classifiers (SVM coefficients)"}
    return ", ".join(names.get(b, b) for b in dict.fromkeys(bad))


def on_main_thread() -> bool:
    """Whether this is the main thread (only it can install a SIGINT handler)."""
    return threading.current_thread() is threading.main_thread()

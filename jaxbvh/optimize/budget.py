"""Time budgets for the optimizers: a wall-clock limit whose clock starts after the first step.

An optimizer's first step (a pass, a chunk of passes, an iteration) also compiles its
programs, so the budget counts from the end of that step: compiling is not spent from it.
The optimizers ask after every step; a run therefore stops at the end of the step that
crosses the limit (it may overshoot by one step).
"""

from __future__ import annotations

import time


class TimeBudget:
    """``seconds`` of wall-clock time after the first step (``None``: no limit)."""

    def __init__(self, seconds: float | None):
        self.seconds = seconds
        self.deadline = None

    def spent(self) -> bool:
        """Call after each step: True once the budget is used up; the first call starts the clock."""
        if self.seconds is None:
            return False
        if self.deadline is None:
            self.deadline = time.perf_counter() + self.seconds
            return False
        return time.perf_counter() > self.deadline

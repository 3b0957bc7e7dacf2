"""A run's wall-clock budget over its phases (`TrainConfig.budget_min`): whether a phase may take
another step, and how far through its allotment it is. Only training time counts: checkpoints,
renders and evaluations are not in `elapsed`."""

from __future__ import annotations

from model.methods import Method
from model.methods.schedules import phase_progress


class Budget:
    def __init__(self, budget_min: float | None, method: Method):
        self.seconds = None if budget_min is None else budget_min * 60
        self.method = method

    def left(self, phase: str, elapsed: dict[str, float], phase_step: int = 0) -> bool:
        """A phase with a share of the budget (LeCO's phase 1) stops at that share, once it has
        taken its minimum steps (while the whole budget lasts); the others stop when the whole
        budget is spent."""
        if self.seconds is None:
            return True
        share = self.method.budget_share(phase)
        within = sum(elapsed.values()) < self.seconds
        if share is not None:
            short = phase_step < self.method.budget_min_steps(phase)
            return elapsed.get(phase, 0.0) < share * self.seconds or (short and within)
        return within

    def progress(self, phase: str, phase_step: int, elapsed: dict[str, float]) -> float:
        """Fraction of the phase done: of its steps, or under a budget of its training-time
        allotment (a phase with a share: that share of the budget; the others: whatever the phases
        before them left), whichever is larger."""
        allotted = None
        if self.seconds is not None:
            share = self.method.budget_share(phase)
            before = self.method.phases[: self.method.phases.index(phase)]
            allotted = (
                share * self.seconds
                if share is not None
                else self.seconds - sum(elapsed.get(p, 0.0) for p in before)
            )
        return phase_progress(
            phase_step,
            self.method.phase_steps(phase),
            elapsed.get(phase, 0.0),
            allotted,
            self.method.budget_min_steps(phase) if self.seconds is not None else 0,
        )

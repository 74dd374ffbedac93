"""The request's work budget (`PRECOND_MAX_WORK_POINTS`) as the engine's own loops spend it.

The gateway estimates an action's points (demonstration positions × argument tuples) from the text, the
sandbox counts them exactly, and both refuse past the budget. The unit of work is one candidate judged at one
point: that is what the sandbox spends on every candidate, and what the engine's own loops over candidates
cost in the worker (a bitset per candidate over the points, the ranking's clusters, the disjunction search's
passes over its atoms). The model's samples and the request's own rules are few (bounded by the request's
schema); the enumerator is the only source whose count grows with the spec, so it is the one cut to the
budget: an action's enumerated candidates × (its points + `COMPILE_POINTS`) stay within it.
"""

from __future__ import annotations

from dataclasses import dataclass

from precond.sandbox.types import ActionInfo, TraceResult

COMPILE_POINTS = 64
"""What a candidate costs before it is judged anywhere (read, compiled, sent, reported), in points: with an
action of one point the budget still bounds how many strings the worker builds."""


def points_of(trace: TraceResult, info: ActionInfo) -> int:
    """An upper bound of the action's default points, known before the sandbox computes them: every position
    of every demonstration × the argument tuples the demonstrations passed (at least one)."""
    return sum(len(positions) for positions in trace.positions) * max(1, len(info.arg_values))


@dataclass(frozen=True)
class WorkBudget:
    points: int
    """`PRECOND_MAX_WORK_POINTS`: what one action's candidates may cost, in candidate × point judgments."""

    def enumerated(self, n_points: int) -> int:
        """How many candidates the enumerator may build for an action of `n_points` points."""
        return self.points // (n_points + COMPILE_POINTS)

    def stopped(self, built: int, n_points: int) -> str:
        """The action's report line when its enumeration was cut at the budget."""
        return (f"the enumerator stopped at {built:,} conditions: each is judged at about {n_points:,} points, "
                f"and {built:,} x ({n_points:,} + {COMPILE_POINTS}) reaches the work budget of {self.points:,} "
                f"(PRECOND_MAX_WORK_POINTS); send fewer demonstrations or fewer distinct arguments for more")

"""Where a tool call's conditions are judged: the points that decide something, not every point of the logs.

An action's default points are every position of every demonstration × every argument tuple the demonstrations
passed it (`PointGrid`): with 150 tool-calling runs of ~20 steps and ~75 distinct calls that is 130,000+ points a
candidate, so the work budget (`PRECOND_MAX_WORK_POINTS`) stops the enumerator after a dozen conditions and a
single slow condition outlives the sandbox's timeout. Almost all of those points pair a step of one run with the
arguments of a call made in another, which no guard is ever asked about. A condition decides something

- at the calls themselves (the occurrences: it must hold there, and labelled calls of the demonstrations are
  among them);
- at the earlier steps of the same run with the same arguments (before the order was read, before the user said
  yes): where the ranking sees what made a condition true just before the call (`ranking.enabled_at`), and where
  a condition that holds anyway is told from one that the run had to bring about;
- and, for the evidence that a condition is not true everywhere (`engine.evidence`), at a bounded sample of the
  other points, MAX_SAMPLE of them, drawn with a fixed seed so that the same request gets the same points.

A grid that is small anyway (at most MAX_SAMPLE points beyond the decisive ones) keeps its default points:
nothing is gained by leaving any out.
"""

from __future__ import annotations

import random
from collections.abc import Sequence

from precond.sandbox.types import ActionInfo, Point, PointGrid, TraceResult

MAX_SAMPLE = 2048
"""Other points a condition is judged at beyond the decisive ones, at most: enough that the chance test of
`engine.evidence` separates a condition holding at every call from one holding almost everywhere (a share
of 1/2048 is below every threshold it uses), few enough that a candidate costs ~1/30 of the full grid."""


def decisive_points(trace: TraceResult, info: ActionInfo, cls_methods: Sequence[str]) -> list[Point] | None:
    """The action's points (above), or None where its default grid is no bigger than them plus the sample.
    `cls_methods`: the action's class's methods, whose first call in a run says from which step the agent
    exists (before it there is no `self` to judge)."""
    values = _values(info)
    grid = sum(len(p) for p in trace.positions) * len(values)
    starts = _starts(trace, cls_methods)
    decisive = _decisive(info, starts)
    if grid <= len(decisive) + MAX_SAMPLE:
        return None
    positions = [(d, p) for d, start in starts.items() for p in range(start, len(trace.positions[d]))]
    full = PointGrid(positions, values)
    chosen = set(decisive)
    rng = random.Random(f"{info.name}:{len(full)}")
    sample: list[Point] = []
    for k in rng.sample(range(len(full)), min(len(full), MAX_SAMPLE + len(decisive))):
        point = full[k]
        if point not in chosen and len(sample) < MAX_SAMPLE:
            chosen.add(point)
            sample.append(point)
    return [*decisive, *sorted(sample, key=_order)]


def _values(info: ActionInfo) -> list[tuple[object, ...]]:
    return list(dict.fromkeys(info.arg_values)) or [()]


def _decisive(info: ActionInfo, starts: dict[int, int]) -> list[Point]:
    """Each call, and every earlier step of its run (since the agent exists) with its arguments, in run order."""
    found: dict[Point, None] = {}
    for occ in info.occurrences:
        for position in range(starts.get(occ.demo, 0), occ.position + 1):
            found.setdefault(Point(occ.demo, position, occ.args))
    return sorted(found, key=_order)


def _starts(trace: TraceResult, cls_methods: Sequence[str]) -> dict[int, int]:
    """Per run, the step of the first call of one of the class's methods (where its object exists)."""
    starts: dict[int, int] = {}
    for name in cls_methods:
        action = trace.actions.get(name)
        for occ in action.occurrences if action else ():
            starts[occ.demo] = min(starts.get(occ.demo, occ.position), occ.position)
    return starts


def _order(point: Point) -> tuple[int, int, str]:
    return point.demo, point.position, repr(point.args)

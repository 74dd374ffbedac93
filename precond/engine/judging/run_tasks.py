"""Which task each run of a request belongs to, told from the runs alone.

A request's runs carry no task ids, yet choosing a rule from labelled calls must know them: a condition that
refuses only one task's calls labelled 'refuse' is a value that task shows, not a reason
(`own_task`). Runs of one task deal with the same user or record: the arguments of a run's first
tool call (`agent.get_user_details('mia_li_3668')`) show up among the calls of every other run of its task, while
a simulated user's first words differ from run to run. So two runs are one task where the constant arguments of
one's first call all occur among the other's calls' constant arguments, and tasks are the connected groups; a
run without a tool call is told by its first words of the user, else by its own name.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Sequence

CALL = re.compile(r"\w+\.(?!says\(|result\()\w+\(")
"""A tool call of a program (`agent.get_order('#1')`), neither a user's words nor a call's logged result."""


def tasks(programs: Sequence[str]) -> list[str]:
    """Per program, the name of its task (module docstring): the key of the first run of its group."""
    calls = [_calls(p) for p in programs]
    firsts = [c[0] if c else None for c in calls]
    seen = [set().union(*c) if c else set() for c in calls]
    parent = list(range(len(programs)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for r, first in enumerate(firsts):
        if not first:
            continue
        for s in range(len(programs)):
            if s != r and first <= seen[s]:
                parent[root(r)] = root(s)
    return [_key(programs[root(k)], k) for k in range(len(programs))]


MIN_TASKS = 3
"""Tasks whose calls labelled 'refuse' a condition must be judged across before one task's are too few
(`own_task`)."""


def across(refused: int, negative: int, task_of: Sequence[str] | None) -> str:
    """How many tasks' labelled calls a condition refuses, for its reason: why a leave-one-task-out choice kept it."""
    if task_of is None or len({task_of[k] for k in _bits(negative)}) < MIN_TASKS:
        return ""
    return (f" (of {len({task_of[k] for k in _bits(refused)})} tasks; chosen leave-one-task-out: a condition "
            "refusing one task's calls alone is not)")


def own_task(refused: int, negative: int, task_of: Sequence[str] | None) -> bool:
    """Whether the calls labelled 'refuse' a condition refuses (`refused`) all come from one task while the
    labelled calls span at least MIN_TASKS tasks: left out, that task's calls would never have chosen it, so a
    leave-one-task-out choice never keeps it (it separates only its own task, as a value only that task shows)."""
    if task_of is None or not refused:
        return False
    spanned = {task_of[k] for k in _bits(negative)}
    return len(spanned) >= MIN_TASKS and len({task_of[k] for k in _bits(refused)}) == 1


def _bits(mask: int) -> list[int]:
    return [k for k in range(mask.bit_length()) if (mask >> k) & 1]


def _calls(program: str) -> list[frozenset[str]]:
    """Per tool call line, its constant arguments (as text, so that 7 and '7' never meet)."""
    out = []
    for line in program.splitlines():
        line = line.strip()
        if not CALL.match(line):
            continue
        try:
            node = ast.parse(line, mode="eval").body
        except SyntaxError:
            continue
        if isinstance(node, ast.Call):
            out.append(frozenset(repr(a.value) for a in [*node.args, *(k.value for k in node.keywords)]
                                 if isinstance(a, ast.Constant)))
    return out


def _key(program: str, k: int) -> str:
    lines = [line.strip() for line in program.splitlines()]
    return next((line for line in lines if CALL.match(line)),
                next((line for line in lines if ".says(" in line), f"run {k}"))

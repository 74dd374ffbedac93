"""Realistic agent errors injected into SGD demonstrations, and random demonstration subsets, for the noise and
sparsity sweep (`precond eval preconditions --configs noise`, docs/method.md "Evidence-weighted validation").

Human agents slip at a few percent of their steps. At a share `rate` of the system steps (system acts and
service calls; `set_query_status` is the environment's answer, never touched) one of these errors replaces
the step, chosen uniformly among those that apply there:

* re-ask: `system.REQUEST(slot)` for a slot the user already informed;
* against the API: `system.NOTIFY_SUCCESS()` after a failed call, `system.NOTIFY_FAILURE()` after a
  successful one;
* drop: the step is left out;
* duplicate: the step is said twice.

Only the demonstrations change; the test dialogs and the ground truth are untouched, so the score says how
much the errors mislead inference. Everything is seeded: the same (rate, seed) gives the same programs.
"""

from __future__ import annotations

import random
import re
from collections.abc import Sequence

SETUP = 2
_STEP = re.compile(r"^(?P<actor>user|system)\.(?P<act>\w+)\((?P<arg>.*)\)$")
ERRORS = ("re-ask", "against the API", "drop", "duplicate")


def sample(demonstrations: Sequence[str], count: int, seed: int) -> list[str]:
    """`count` of the demonstrations, drawn without replacement by `seed`, in their original order."""
    if count >= len(demonstrations):
        return list(demonstrations)
    chosen = sorted(random.Random(seed).sample(range(len(demonstrations)), count))
    return [demonstrations[i] for i in chosen]


def corrupt(demonstrations: Sequence[str], rate: float, seed: int) -> list[str]:
    """The demonstrations with errors at `round(rate x system steps)` of their system steps."""
    rng = random.Random(f"noise|{rate}|{seed}")
    lines = [d.splitlines() for d in demonstrations]
    steps = [(i, k) for i, program in enumerate(lines) for k, line in enumerate(program)
             if k >= SETUP and _is_system_step(line)]
    chosen = set(rng.sample(steps, min(len(steps), round(rate * len(steps))))) if rate > 0 else set()
    out = []
    for i, program in enumerate(lines):
        new: list[str] = []
        for k, line in enumerate(program):
            new.extend(_error(program, k, rng) if (i, k) in chosen else [line])
        out.append("\n".join(new) + "\n")
    return out


def _is_system_step(line: str) -> bool:
    match = _STEP.match(line.strip())
    return bool(match and match["actor"] == "system" and match["act"] != "set_query_status")


def _error(program: Sequence[str], k: int, rng: random.Random) -> list[str]:
    options: list[list[str]] = [[], [program[k], program[k]]]
    informed = _informed(program[:k])
    if informed:
        options.append([f"system.REQUEST({rng.choice(sorted(informed))})"])
    status = _last_status(program[:k])
    if status is not None:
        options.append(["system.NOTIFY_FAILURE()" if status else "system.NOTIFY_SUCCESS()"])
    return rng.choice(options)


def _informed(before: Sequence[str]) -> set[str]:
    found = set()
    for line in before:
        match = _STEP.match(line.strip())
        if match and match["actor"] == "user" and match["act"] == "INFORM":
            found.add(match["arg"])
    return found


def _last_status(before: Sequence[str]) -> bool | None:
    for line in reversed(before):
        match = _STEP.match(line.strip())
        if match and match["act"] == "set_query_status":
            return match["arg"] == "True"
    return None

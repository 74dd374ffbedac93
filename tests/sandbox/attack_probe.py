"""Attacks on the sandbox boundary from code that first switches off every Python-level guard.

Run by test_boundary.py in-process and, as a separate program, under another (non-root) uid: it prints
one JSON object, attack name -> outcome ("denied: ..." or "ALLOWED: ..."). Kept as a plain script so the
same attacks run unchanged in both deployments.
"""

from __future__ import annotations

import json
import os
import sys

from precond.sandbox import Limits, Sandbox
from precond.stack.hostile_corpus import ATTACKS, GUARDS_OFF

SPEC = "class A:\n    def __init__(self):\n        self.x = 1\n    def act(self, v):\n        pass\n"
CANARY = "/tmp/sandbox_boundary_canary"

ATTACK = GUARDS_OFF + ATTACKS.replace('CANARY', repr(CANARY))


def run_attacks(sandbox: Sandbox) -> dict[str, str]:
    if os.path.exists(CANARY):
        os.unlink(CANARY)
    trace = sandbox.trace(SPEC, [ATTACK])
    (values,) = trace.actions["A.act"].arg_values
    outcome: dict[str, str] = eval(str(values[0]), {"__builtins__": {}})  # a dict literal of strings
    outcome["canary file exists"] = "ALLOWED" if os.path.exists(CANARY) else "denied"
    return outcome


if __name__ == "__main__":
    with Sandbox(Limits(timeout_s=20, cpu_s=10), workers=1) as box:
        print(json.dumps({"uid": os.getuid(), "results": run_attacks(box)}))
    sys.exit(0)

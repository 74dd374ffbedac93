"""Data and code shared by the sandbox tests (a module of its own: conftest is not importable)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sandbox import Limits

DATA = Path(__file__).resolve().parents[1] / "fixtures" / "data"
SMALL = Limits(timeout_s=3.0, cpu_s=2, memory_mb=512, output_bytes=100_000, recursion=200)

# The spec counts, in a module every child shares with the server's import, how often `mark` ran in this
# process: a fresh child always sees 1 after the history below, a reused one more. (The rule reads the count
# from the object: a plain rule, judged in the call's first child, the one a scope's warm child can answer.)
COUNTING_SPEC = """
import collections

class Room:
    def mark(self):
        collections.marks = getattr(collections, 'marks', 0) + 1
        self.marks = collections.marks
    def enter(self):
        pass
"""


def sgd(domain: str) -> dict[str, Any]:
    return json.loads((DATA / "sgd" / f"{domain}.json").read_text())


def alfworld(name: str) -> dict[str, Any]:
    return json.loads((DATA / "alfworld" / name).read_text())

"""Data and code shared by the sandbox tests (a module of its own: conftest is not importable)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from precond.sandbox import Limits

DATA = Path(__file__).resolve().parents[1] / "fixtures" / "data"
SMALL = Limits(timeout_s=3.0, cpu_s=1, unit_cpu_s=1.0, memory_mb=512, output_bytes=100_000, recursion=200)
"""Limits a hostile loop runs into within a second of CPU: that it is stopped is what the tests prove, not after
how long."""


def sgd(domain: str) -> dict[str, Any]:
    return json.loads((DATA / "sgd" / f"{domain}.json").read_text())


def alfworld(name: str) -> dict[str, Any]:
    return json.loads((DATA / "alfworld" / name).read_text())

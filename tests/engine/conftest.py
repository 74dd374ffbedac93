"""Shared data for the engine tests: read from ../shared (never copied into the project)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"


@pytest.fixture(scope="module")
def restaurants() -> dict[str, Any]:
    data: dict[str, Any] = json.loads((SHARED / "sgd" / "Restaurants_1.json").read_text())
    return data

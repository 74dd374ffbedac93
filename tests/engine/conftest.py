"""Data for the engine tests: the repository's fixtures (tests/fixtures), a subset of the development data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

SHARED = Path(__file__).resolve().parents[1] / "fixtures" / "data"


@pytest.fixture(scope="module")
def restaurants() -> dict[str, Any]:
    data: dict[str, Any] = json.loads((SHARED / "sgd" / "Restaurants_1.json").read_text())
    return data

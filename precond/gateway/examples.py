"""Request examples for the OpenAPI document, read from the bodies in examples/ so docs and files agree."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

EXAMPLES_DIR = Path(__file__).resolve().parents[2] / "examples"


def openapi_examples(*names: str) -> dict[str, Any]:
    """`{name: {summary, value}}` for the named example files; missing files are left out, not invented."""
    found = {}
    for name in names:
        path = EXAMPLES_DIR / f"{name}.json"
        if path.is_file():
            found[name] = {"summary": name.replace("-", " "), "value": json.loads(path.read_text())}
    return found

"""A directory of JSON files keyed by path: every expensive result is written as soon as it exists.

Runs are resumable because each unit of work (one inference per domain and configuration, one policy turn,
one batch of satisfaction sets) is a file; a crash loses at most the unit in flight. Writes go through a
temporary file and a rename, so an interrupted run never leaves a truncated JSON behind.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

DEFAULT_CACHE = Path(".eval-cache")
_UNSAFE = re.compile(r"[^A-Za-z0-9_.+=-]+")


def slug(text: str) -> str:
    return _UNSAFE.sub("_", text).strip("_") or "_"


class JsonCache:
    def __init__(self, root: Path = DEFAULT_CACHE) -> None:
        self.root = root

    def path(self, *parts: str) -> Path:
        return self.root.joinpath(*(slug(p) for p in parts[:-1]), slug(parts[-1]) + ".json")

    def get(self, *parts: str) -> Any | None:
        path = self.path(*parts)
        if not path.exists():
            return None
        return json.loads(path.read_text(encoding="utf-8"))

    def put(self, value: Any, *parts: str) -> Path:
        path = self.path(*parts)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".json")
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            json.dump(value, handle, indent=1, sort_keys=True)
        os.replace(tmp, path)
        return path

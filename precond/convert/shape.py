"""Reading JSON of an expected shape, with errors that name the file and the key where it is wrong."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from precond_client.openai_log import ConvertError

__all__ = ["ConvertError", "at", "expect", "key", "load_json"]


def load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConvertError(f"{path}: cannot read: {exc.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConvertError(f"{path}: not JSON: {exc}") from None


def at(path: Path, where: str) -> str:
    return f"{path}: {where}" if where else str(path)


def expect(value: Any, kind: type | tuple[type, ...], path: Path, where: str) -> Any:
    if not isinstance(value, kind):
        names = " or ".join(k.__name__ for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise ConvertError(f"{at(path, where or 'top level')}: expected {names}, found {type(value).__name__}")
    return value


def key(obj: dict[str, Any], name: str, kind: type | tuple[type, ...], path: Path, where: str) -> Any:
    if name not in obj:
        raise ConvertError(f"{at(path, where or 'top level')}: missing key {name!r}")
    return expect(obj[name], kind, path, f"{where}.{name}" if where else name)

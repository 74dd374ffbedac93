"""Write `precond_client/sync.py` from `precond_client/aio.py`: one implementation of the client, two faces.

The blocking `Client` is the asyncio `AsyncClient` with the awaits taken out (the approach of httpcore's
`unasync`): editing both by hand let them drift. `python scripts/unasync_client.py` rewrites sync.py;
`--check` exits 1 when sync.py is not what aio.py gives (a test runs it).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "precond_client" / "aio.py"
TARGET = ROOT / "precond_client" / "sync.py"

DOCSTRINGS = (
    ('"""`AsyncClient`: the asyncio client (httpx). The blocking `Client` (sync.py) is written from this file by\n'
     '`scripts/unasync_client.py`: edit this one."""',
     '"""`Client`: the blocking client (httpx). Written from aio.py by `scripts/unasync_client.py`: do not edit."""'),
    ("An asyncio client of the precondition service; every method of `Client`, awaited.",
     "A blocking client of the precondition service."),
)
WORDS = (  # in order: the longer spellings first
    (r"import asyncio\n", ""),
    (r"\basyncio\.sleep\(", "time.sleep("),
    (r"\bAsyncClient\b", "Client"),
    (r"\basync with\b", "with"),
    (r"\basync def\b", "def"),
    (r"\bawait ", ""),
    (r"\.aclose\(\)", ".close()"),
    (r"__aenter__", "__enter__"),
    (r"__aexit__", "__exit__"),
    (r"\((self\._send\([^()]*\))\)", r"\1"),  # `(await self._send(...)).json()` without its await
)


def unasync(text: str) -> str:
    for old, new in DOCSTRINGS:
        if old not in text:
            raise SystemExit(f"aio.py no longer contains {old[:60]!r}...: update scripts/unasync_client.py")
        text = text.replace(old, new)
    for pattern, replacement in WORDS:
        text = re.sub(pattern, replacement, text)
    return text


def main() -> None:
    wanted = unasync(SOURCE.read_text(encoding="utf-8"))
    if "--check" in sys.argv[1:]:
        if TARGET.read_text(encoding="utf-8") != wanted:
            raise SystemExit("precond_client/sync.py is not what aio.py gives: run python scripts/unasync_client.py")
        return
    TARGET.write_text(wanted, encoding="utf-8")


if __name__ == "__main__":
    main()

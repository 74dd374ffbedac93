"""The blocking client is the asyncio client with the awaits taken out, never a second copy to keep in step."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_sync_client_is_written_from_the_async_one() -> None:
    result = subprocess.run([sys.executable, "scripts/unasync_client.py", "--check"], cwd=ROOT,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_the_written_client_blocks() -> None:
    """Nothing of asyncio is left in it (a rule of the rewrite that stopped matching would leave some)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import unasync_client
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    generated = unasync_client.unasync((ROOT / "precond_client" / "aio.py").read_text(encoding="utf-8"))
    assert "await " not in generated and "async def" not in generated and "asyncio" not in generated
    assert "class Client:" in generated and "httpx.Client(" in generated and "time.sleep(" in generated

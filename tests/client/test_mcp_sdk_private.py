"""What the proxy takes from the MCP SDK's private helpers (precond_client/mcp/sdk_private.py): each does what the
proxy's own `tools/call` path relies on, on the SDK version installed; a version outside the extra's bounds, or a
helper that changed, fails here rather than in a user's proxy."""

from __future__ import annotations

import os
import sys
import time
from importlib.metadata import version
from pathlib import Path

import anyio
import pytest

pytest.importorskip("mcp")

from mcp_types.version import KNOWN_PROTOCOL_VERSIONS

from precond.stack.harness import alive
from precond_client.mcp import sdk_private


def stubborn(pids: Path) -> str:
    """A process that ignores SIGTERM and its closed stdin, with a child; it writes both pids to `pids`."""
    return (
        "import os, signal, subprocess, sys, time\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)'])\n"
        f"open({str(pids)!r}, 'w').write(f'{{os.getpid()}} {{child.pid}}')\n"
        "time.sleep(600)\n"
    )


def assert_ended(pids: Path) -> None:
    for pid in map(int, pids.read_text().split()):
        for _ in range(100):
            if not alive(pid):
                break
            time.sleep(0.05)
        assert not alive(pid), f"process {pid} outlived the stop"


def test_the_installed_sdk_is_the_minor_version_the_helpers_were_read_in() -> None:
    installed = version("mcp").split(".")
    assert ".".join(installed[:2]) == sdk_private.SDK_CHECKED


def test_a_negative_cache_lifetime_is_floored_and_other_fields_are_left_alone() -> None:
    raw = {"content": [], "ttlMs": -5, "isError": False}
    sdk_private.clamp_inbound_ttl(raw)
    assert raw == {"content": [], "ttlMs": 0, "isError": False}
    kept = {"content": [], "ttlMs": 7}
    sdk_private.clamp_inbound_ttl(kept)
    assert kept == {"content": [], "ttlMs": 7}


def test_fields_of_later_revisions_are_named_for_older_sessions_only() -> None:
    oldest, newest = KNOWN_PROTOCOL_VERSIONS[0], KNOWN_PROTOCOL_VERSIONS[-1]
    later = sdk_private.later_revision_fields("tools/call", oldest)
    assert later and not later & {"content", "isError", "structuredContent"}
    assert sdk_private.later_revision_fields("tools/call", newest) == frozenset()


def test_a_process_that_ignores_its_closed_stdin_is_ended_with_its_children(tmp_path) -> None:
    pids = tmp_path / "pids"
    script = stubborn(pids)

    async def run() -> None:
        process = await anyio.open_process([sys.executable, "-c", script], start_new_session=True)
        while not pids.exists() or not pids.read_text():
            await anyio.sleep(0.05)
        await sdk_private.stop_server_process(process)

    anyio.run(run)
    assert_ended(pids)


def test_a_process_on_the_callers_own_pipes_is_stopped_as_the_sdk_stops_one(tmp_path) -> None:
    """`stop_piped_process`: the SDK's stop, handed the caller's pipes: stdin closed first (a process that exits at
    its end of input goes in the grace period), stdout after, and one that ignores both is ended with its
    children."""
    pids = tmp_path / "pids"
    script = stubborn(pids)
    closed: list[str] = []

    async def stop(code: str) -> float:
        stdin, to_child = os.pipe()
        process = await anyio.open_process([sys.executable, "-c", code], stdin=stdin, start_new_session=True)
        os.close(stdin)
        while code == script and (not pids.exists() or not pids.read_text()):
            await anyio.sleep(0.05)
        started = time.monotonic()
        await sdk_private.stop_piped_process(process, lambda: (closed.append("stdin"), os.close(to_child)),
                                             lambda: closed.append("stdout"))
        assert process.returncode is not None
        return time.monotonic() - started

    assert anyio.run(stop, "import sys; sys.stdin.read()") < 1.5
    assert closed == ["stdin", "stdout"]
    anyio.run(stop, script)
    assert_ended(pids)

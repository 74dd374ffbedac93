"""The MCP SDK's private helpers the proxy's own `tools/call` path reuses, so that it checks a result and stops a
process exactly as the SDK's session does; imported here only, and checked when imported.

They are not the SDK's public API: the extra bounds the SDK to the minor version they were read in
(`SDK_CHECKED`), and a version that lacks one stops `precond mcp` at import with an error naming the helper and
the installed version (never a silently different check). tests/client/test_mcp_sdk_private.py checks what each
one does.
"""

from __future__ import annotations

from importlib.metadata import version

SDK_CHECKED = "2.3"
"""The `mcp` minor version these helpers were read in (pyproject's `mcp>=2.3,<2.4`)."""

try:
    from mcp.client.session import _clamp_inbound_ttl as clamp_inbound_ttl
    from mcp.client.session import _later_revision_fields as later_revision_fields
    from mcp.client.stdio import _stop_server_process as stop_server_process
except ImportError as error:  # pragma: no cover - only on an SDK outside the extra's bounds
    raise ImportError(
        f"precond mcp reuses private helpers of the MCP SDK read in mcp {SDK_CHECKED}.x; the installed mcp "
        f"{version('mcp')} lacks one ({error}): install the extra's bounds (pip install 'precond-client[mcp]')"
    ) from error

__all__ = ["SDK_CHECKED", "clamp_inbound_ttl", "later_revision_fields", "stop_server_process"]

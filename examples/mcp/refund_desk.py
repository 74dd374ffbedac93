"""A tiny refund desk as an MCP server (the official SDK's `MCPServer`): three tools over an in-memory order
book, for docs/mcp.md's walkthrough and the proxy's tests. Every refund reads the order first in a careful
agent's sessions; `precond mcp` learns that from recorded sessions and refuses a refund of an order never read.

    python examples/mcp/refund_desk.py              # MCP on stdio
    python examples/mcp/refund_desk.py --http 9000  # streamable HTTP on http://127.0.0.1:9000/mcp
"""

from __future__ import annotations

import argparse
from typing import Any

from mcp.server import MCPServer
from mcp.server.mcpserver.exceptions import ToolError

ORDERS: dict[str, dict[str, Any]] = {
    "A100": {"order_id": "A100", "status": "delivered", "amount": 40, "refunded": 0},
    "A200": {"order_id": "A200", "status": "delivered", "amount": 25, "refunded": 0},
    "A300": {"order_id": "A300", "status": "shipped", "amount": 90, "refunded": 0},
}

desk = MCPServer("refund-desk")


@desk.tool()
def get_order(order_id: str) -> dict[str, Any]:
    """Read an order: its status, amount and what was refunded already."""
    if order_id not in ORDERS:
        raise ToolError(f"no order {order_id}")
    return dict(ORDERS[order_id])


@desk.tool()
def refund_order(order_id: str, amount: int) -> dict[str, Any]:
    """Refund part or all of an order's amount."""
    order = ORDERS[order_id]
    order["refunded"] += amount
    return {"order_id": order_id, "refunded": order["refunded"]}


@desk.tool()
def send_note(order_id: str, text: str) -> str:
    """Send the customer a note about an order."""
    return f"note sent for {order_id}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--http", type=int, metavar="PORT", help="serve streamable HTTP on 127.0.0.1:PORT")
    args = parser.parse_args()
    if args.http is None:
        desk.run()
    else:
        desk.run("streamable-http", host="127.0.0.1", port=args.http)


if __name__ == "__main__":
    main()

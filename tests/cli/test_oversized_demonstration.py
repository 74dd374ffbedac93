"""A demonstration too large to judge is left out and named; the other demonstrations still teach.

The domain is built here from scratch in OpenAI's tool-calling format (a shop's support agent: read an order,
then refund or cancel it), converted with `precond convert openai`, and learned with `precond infer`. One run's
order read returns a large record; the sandbox's result limit is set below what that run's trace answers (a
limit that a size hits, as a time limit does, but the same on a loaded machine), so it hits a limit alone.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

from tests.cli.inprocess import precond

RESULT_LIMIT = "100000"

TOOLS = [
    {"type": "function", "function": {"name": name, "description": description, "parameters": {
        "type": "object", "properties": properties, "required": list(properties)}}}
    for name, description, properties in (
        ("get_order_details", "Read an order.", {"order_id": {"type": "string"}}),
        ("refund_order", "Refund an order.", {"order_id": {"type": "string"}, "amount": {"type": "number"}}),
        ("cancel_order", "Cancel an order.", {"order_id": {"type": "string"}}),
    )
]


def _call(tool: str, arguments: dict[str, Any], content: dict[str, Any]) -> list[dict[str, Any]]:
    return [{"role": "assistant", "content": None, "tool_calls": [
                {"id": f"call_{tool}", "type": "function",
                 "function": {"name": tool, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "tool_call_id": f"call_{tool}", "name": tool, "content": json.dumps(content)}]


def shop_runs(count: int, large: set[int]) -> list[list[dict[str, Any]]]:
    """`count` good runs; in those of `large`, the order read lists 1,500 items (about 70 kB of result)."""
    runs = []
    for k in range(count):
        order: dict[str, Any] = {"order_id": f"O{k}", "status": "pending", "total": 10.0 + k}
        if k in large:
            order["items"] = [{"sku": f"S{j}", "quantity": j % 5, "price": 1.5} for j in range(1_500)]
        write = _call("cancel_order", {"order_id": f"O{k}"}, {"ok": True}) if k % 2 else \
            _call("refund_order", {"order_id": f"O{k}", "amount": order["total"]}, {"ok": True})
        runs.append([{"role": "user", "content": f"help with order O{k}"},
                     *_call("get_order_details", {"order_id": f"O{k}"}, order), *write])
    return runs


def learn(tmp_path: Path, runs: list[list[dict[str, Any]]], monkeypatch: pytest.MonkeyPatch
          ) -> subprocess.CompletedProcess[str]:
    (tmp_path / "trajectories.json").write_text(json.dumps(runs))
    (tmp_path / "tools.json").write_text(json.dumps(TOOLS))
    monkeypatch.setenv("SANDBOX_RESULT_BYTES", RESULT_LIMIT)
    converted = precond("convert", "openai", str(tmp_path / "trajectories.json"), "--tools",
                        str(tmp_path / "tools.json"), "--out", str(tmp_path / "shop"), "--writes",
                        "refund_order,cancel_order", "--guard", "refund_order,cancel_order")
    assert converted.returncode == 0, converted.stderr
    request = json.loads((tmp_path / "shop" / "request.json").read_text())
    request["options"] = {"generators": ["enumerate"]}
    return precond("infer", "-", stdin=json.dumps(request))


def test_one_oversized_demonstration_is_left_out_by_name_and_the_others_teach_every_action(tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    done = learn(tmp_path, shop_runs(20, {12}), monkeypatch)
    assert done.returncode == 0, done.stderr
    answer = json.loads(done.stdout)
    warning = answer["warnings"]["demonstrations[12]"]
    assert "left out" in warning and "result limit" in warning and "SANDBOX_RESULT_BYTES" in warning
    assert "other 19 demonstration(s)" in warning
    assert f"WARNING demonstrations[12]: {warning}" in done.stderr
    for action in ("AGENT.refund_order", "AGENT.cancel_order"):
        assert "order_id in self.results['get_order_details']" in answer["preconditions"][action], action
    occurrences = {a: {e.get("occurrences") for e in rules.values()} for a, rules in answer["evidence"].items()}
    assert occurrences == {"AGENT.refund_order": {9}, "AGENT.cancel_order": {10}}  # run 12 (a refund) not counted


def test_the_inference_fails_with_the_limit_only_when_no_demonstration_is_left(tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    done = learn(tmp_path, shop_runs(2, {0, 1}), monkeypatch)
    assert done.returncode == 3
    assert "result limit" in done.stderr and "Traceback" not in done.stderr

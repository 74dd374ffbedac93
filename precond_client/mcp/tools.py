"""The upstreams' MCP tools as what `precond convert openai` reads: OpenAI function schemas (the proxy writes
them to `tools.json` beside the recorded sessions), and as the spec that command writes from them, so that the
rules an inference printed can be judged by the embedded guard without a spec file.

`agent_tools` reads the schemas as `precond.convert.openai.read_tools` does (required parameters in the schema's
order, then the optional ones; the description as docstring; names as Python binds them; the parameters' JSON
Schema, which the spec keeps and the guard checks arguments against); a test holds the two
to the same spec text, since the guard refuses any spec but the converter's, character for character.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from mcp import types as mcp_types

from precond_client.openai_log import Tool, python_name, spec_program, writes_of


def function_schema(tool: mcp_types.Tool) -> dict[str, Any]:
    """`{"type": "function", "function": {name, description, parameters}}`: the input schema unchanged."""
    return {"type": "function", "function": {"name": tool.name, "description": tool.description or "",
                                             "parameters": dict(tool.input_schema)}}


def agent_tools(schemas: Sequence[Mapping[str, Any]]) -> list[Tool]:
    """The spec's tools from the OpenAI schemas, in the converter's reading of them."""
    tools = []
    for schema in schemas:
        function = schema["function"]
        parameters = function.get("parameters") or {}
        properties = [python_name(p) for p in parameters.get("properties", {})]
        required = {python_name(r) for r in parameters.get("required", [])}
        ordered = [p for p in properties if p in required] + [p for p in properties if p not in required]
        tools.append(Tool(python_name(function["name"]), tuple(ordered), frozenset(required),
                          function.get("description") or "", dict(parameters) or None))
    return tools


def default_writes(schemas: Sequence[Mapping[str, Any]]) -> set[str]:
    """The state-changing tools `precond convert openai` counts by default (named like writes: book_, cancel_,
    ...): its spec, and so the spec the rules were learned over, has them as `WRITES`. Which tools have rules
    says nothing of it, since every tool is guarded by default."""
    return writes_of(agent_tools(schemas))


def spec_for(schemas: Sequence[Mapping[str, Any]], writes: Iterable[str] | None = None) -> str:
    """The converter's spec of these tools (`writes`: its `--writes`, by default the converter's default)."""
    return spec_program(agent_tools(schemas), default_writes(schemas) if writes is None else writes)

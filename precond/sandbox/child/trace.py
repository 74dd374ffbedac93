"""Trace: where each demonstration's steps are, and where each spec method was called with what."""

from __future__ import annotations

import json
import typing

from precond.programs import Method

from .runtime import Context, Program, load, recorder
from .values import jsonable


def job_trace(payload: dict[str, typing.Any], ctx: Context) -> dict[str, object]:
    spec, demos = load(payload, ctx)
    occurrences: dict[str, list[list[object]]] = {q: [] for q in spec.methods}
    seen: dict[str, dict[str, object]] = {q: {} for q in spec.methods}
    positions = []
    for index, source in enumerate(demos):
        ctx.report.phase(f"demonstrations[{index}]")
        program = Program(spec, source, "demonstration", index, ctx.report)

        def on_call(method: Method, receiver: object, args: tuple[object, ...], p: Program = program) -> None:
            values = jsonable(args)
            occurrences[method.qualname].append([p.index, p.position, values])
            seen[method.qualname].setdefault(json.dumps(values, sort_keys=True), values)

        program.instrument(recorder(program, on_call))
        program.run()
        positions.append(program.positions())
    actions = {
        q: {"params": list(m.signature), "stub": m.stub, "occurrences": occurrences[q],
            "arg_values": list(seen[q].values())}
        for q, m in spec.methods.items()
    }
    return {"positions": positions, "actions": actions}

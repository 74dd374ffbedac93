"""Evaluate: judge assertion candidates at every occurrence of their action, and compute the bitset of
points where each holds. Each candidate is one unit: its result is streamed to the server as soon as it
is known, and a candidate that runs out of memory fails alone."""

from __future__ import annotations

import ast
import copy
import dataclasses
import json
import types
import typing

from precond.programs import Method

from .framing import Reporter
from .runtime import UNDO_LOG, UNDO_ON, Context, Occurrence, Program, Spec, compiled, load, recorder, rollback
from .values import FATAL, Failure, clean, describe, jsonable, tupled


def compile_assertion(expression: object, method: Method, filename: str) -> types.CodeType:
    """`lambda self, <params>: (<expression>)`, built as an AST so that no text is spliced."""
    if not isinstance(expression, str):
        raise SyntaxError("not a string")
    key = ("assertion", expression, tuple(method.positional), method.vararg, filename)
    return typing.cast(types.CodeType, compiled(key, lambda: _assertion_code(expression, method, filename)))


def _assertion_code(expression: str, method: Method, filename: str) -> types.CodeType:
    body = ast.parse(expression, filename, mode="eval").body
    arguments = ast.arguments(
        posonlyargs=[], args=[ast.arg("self")] + [ast.arg(p) for p in method.positional],
        vararg=ast.arg(method.vararg) if method.vararg else None, kwonlyargs=[], kw_defaults=[],
        kwarg=None, defaults=[],
    )
    node = ast.Expression(ast.Lambda(args=arguments, body=body))
    ast.fix_missing_locations(node)
    return compile(node, filename, "eval")


@dataclasses.dataclass
class Candidate:
    """One compiled assertion: a function per demonstration (each has its own spec globals)."""

    pure: bool
    functions: list[typing.Any]


def holds(fn: typing.Any, state: object, args: tuple[object, ...], pure: bool) -> bool:
    """One evaluation; raises what the expression raises. Never lets it change `state` for later ones."""
    UNDO_ON[0] = True  # inline, not a context manager: this runs once per candidate × point
    try:
        return bool(fn(state if pure else copy.deepcopy(state), *args))
    finally:
        UNDO_ON[0] = False
        if UNDO_LOG:
            rollback()


def satisfied(candidate: Candidate, points: list[tuple[int, object, tuple[object, ...]]]) -> str:
    bits = bytearray(b"0" * len(points))
    functions, pure = candidate.functions, candidate.pure
    for k, (demo, state, args) in enumerate(points):
        if state is None:
            continue
        try:
            if holds(functions[demo], state, args, pure):
                bits[k] = 49
        except FATAL:
            raise
        except BaseException:
            pass
    bits.reverse()
    return format(int(bits or b"0", 2), "x")


def first_violation(candidate: Candidate, occurrences: list[Occurrence]) -> str | None:
    for occ in occurrences:
        where = f"demonstrations[{occ.demo}], line {occ.line}, args {clean(repr(jsonable(occ.args)), 200)}"
        if occ.state is None:
            return f"{where}: the state could not be copied"
        try:
            if not holds(candidate.functions[occ.demo], occ.state, occ.args, candidate.pure):
                return f"{where}: assertion fails"
        except FATAL:
            raise
        except BaseException as exc:
            name, message = describe(exc)
            return f"{where}: {name}: {message}"
    return None


def job_evaluate(payload: dict[str, typing.Any], ctx: Context) -> dict[str, object]:
    spec, demos = load(payload, ctx)
    candidates = payload.get("candidates")
    custom = payload.get("points") or {}
    if not isinstance(candidates, dict) or not isinstance(custom, dict):
        raise Failure({"kind": "bad_request", "message": "candidates and points must be objects"})
    wanted = {q for q in candidates if q in spec.methods}
    occurrences: dict[str, list[Occurrence]] = {q: [] for q in wanted}
    programs = []
    for index, source in enumerate(demos):
        ctx.report.phase(f"demonstrations[{index}]")
        programs.append(_observe(spec, index, source, wanted, occurrences, ctx.report))
    points_out: dict[str, object] = {}
    budget = int(payload.get("max_points") or 0)
    unit = 0
    for qname, expressions in candidates.items():
        method = spec.methods.get(qname)
        if method is None or not isinstance(expressions, list):
            for _ in expressions if isinstance(expressions, list) else []:
                if unit not in ctx.skip:
                    ctx.report.unit(unit, {"status": "rejected", "reason": f"unknown action {clean(qname, 100)}"})
                unit += 1
            continue
        ctx.report.phase(f"points of {clean(qname, 100)}")
        if qname in custom:
            _within_budget(qname, len(custom[qname]) if isinstance(custom[qname], list) else 0, budget)
            points = _custom_points(programs, method, custom[qname])
        else:
            values = _default_values(method, occurrences[qname])
            where = _default_positions(programs, method)
            _within_budget(qname, len(where) * len(values), budget)
            points_out[qname] = {"positions": where, "arg_values": [jsonable(v) for v in values]}
            points = [(d, programs[d].self_at(p, method), v) for d, p in where for v in values]
        for number, expression in enumerate(expressions):
            if unit not in ctx.skip:
                ctx.report.begin(unit, f"candidate {number} of {clean(qname, 100)}")
                ctx.report.unit(unit, _judge(spec, programs, method, expression, occurrences[qname], points))
            unit += 1
    return {"points": points_out}
def _within_budget(qname: str, size: int, budget: int) -> None:
    if budget and size > budget:
        raise Failure({"kind": "limit", "limit": "work", "message": (
            f"{clean(qname, 100)}: {size} points (demonstration positions × argument tuples) exceed the "
            f"budget of {budget}; send fewer demonstrations or fewer distinct arguments")})


def _observe(spec: Spec, index: int, source: object, wanted: set[str],
             occurrences: dict[str, list[Occurrence]], report: Reporter) -> Observed:
    program = Program(spec, source, "demonstration", index, report)

    def on_call(method: Method, receiver: object, args: tuple[object, ...]) -> None:
        if method.qualname in wanted:
            state = program.receiver_state(receiver)
            occurrences[method.qualname].append(
                Occurrence(index, program.position, program.call_line(), args, state))

    restore = program.instrument(recorder(program, on_call))
    program.run(snapshot=True)
    restore()
    return Observed(program)


class Observed:
    """A demonstration after its run: snapshots before each position, and where each class has `self`."""

    def __init__(self, program: Program) -> None:
        self.program = program
        self.globals = program.base
        self._selves: dict[tuple[int, str], object] = {}

    def self_at(self, position: int, method: Method) -> object:
        key = (position, method.cls)
        if key not in self._selves:
            cls = self.globals.get(method.cls)
            snapshots = self.program.snapshots
            found = None
            if isinstance(cls, type) and 0 <= position < len(snapshots):
                found = next((v for v in snapshots[position].values() if isinstance(v, cls)), None)
            self._selves[key] = found
        return self._selves[key]


def _default_values(method: Method, occurrences: list[Occurrence]) -> list[tuple[object, ...]]:
    if not method.positional and not method.vararg:
        return [()]
    seen: dict[str, tuple[object, ...]] = {}
    for occ in occurrences:
        values = jsonable(occ.args)
        seen.setdefault(json.dumps(values, sort_keys=True), typing.cast(tuple[object, ...], tupled(values)))
    return list(seen.values())


def _default_positions(programs: list[Observed], method: Method) -> list[list[int]]:
    return [[d, p] for d, obs in enumerate(programs) for p in range(len(obs.program.body))
            if obs.self_at(p, method) is not None]


def _custom_points(programs: list[Observed], method: Method, raw: object
                   ) -> list[tuple[int, object, tuple[object, ...]]]:
    if not isinstance(raw, list):
        raise Failure({"kind": "bad_request", "message": f"points of {method.qualname} must be a list"})
    points = []
    for item in raw:
        demo, position, args = item
        if not (isinstance(demo, int) and 0 <= demo < len(programs)):
            raise Failure({"kind": "bad_request", "message": f"point demonstration {demo!r} out of range"})
        if not (isinstance(position, int) and 0 <= position < len(programs[demo].program.body)):
            raise Failure({"kind": "bad_request", "message": f"point position {position!r} out of range"})
        points.append((demo, programs[demo].self_at(position, method),
                       typing.cast(tuple[object, ...], tupled(args))))
    return points


def _judge(spec: Spec, programs: list[Observed], method: Method, expression: object,
           occurrences: list[Occurrence], points: list[tuple[int, object, tuple[object, ...]]]
           ) -> dict[str, object]:
    try:
        code = compile_assertion(expression, method, "<assertion>")
    except FATAL:
        raise
    except BaseException as exc:
        name, message = describe(exc)
        return {"status": "rejected", "reason": f"{name}: {message}"}
    tree = ast.parse(typing.cast(str, expression), mode="eval")
    try:
        functions = [eval(code, obs.globals) for obs in programs]
        candidate = Candidate(spec.purity.expression_is_pure(tree), functions)
        violation = first_violation(candidate, occurrences)
        return {"status": "valid" if violation is None else "invalid", "reason": violation,
                "satisfied": satisfied(candidate, points)}
    except MemoryError:
        rollback()
        return {"status": "rejected", "reason": "memory limit exceeded while judging this candidate"}

"""Check: run the history as what happened, then judge each proposed call against the preconditions on
its own copy of the state. Each proposed call is one unit."""

from __future__ import annotations

import inspect
import types
import typing

from precond.programs import Method

from .evaluate import compile_assertion
from .runtime import Context, Program, Spec, bind
from .values import FATAL, Failure, clean, describe, tupled


def job_check(payload: dict[str, typing.Any], ctx: Context) -> dict[str, object]:
    ctx.report.phase("spec")
    spec = Spec(payload.get("spec"), ctx.builtins)
    preconditions = payload.get("preconditions")
    calls = payload.get("calls")
    if not isinstance(preconditions, dict) or not isinstance(calls, list):
        raise Failure({"kind": "bad_request", "message": "preconditions must be an object, calls a list"})
    codes = _precondition_codes(spec, preconditions)
    program = Program(spec, payload.get("history"), "history", None, ctx.report)
    guards: dict[str, list[tuple[str, typing.Any]]] = {
        q: [(text, eval(code, program.globals)) for text, code in items] for q, items in codes.items()
    }
    signatures: dict[str, tuple[typing.Any, inspect.Signature]] = {}

    def wrap(method: Method, fn: typing.Any, signature: inspect.Signature) -> typing.Any:
        signatures[method.qualname] = (fn, signature)
        checks = guards.get(method.qualname, [])

        def guarded(self: object, *args: object, **kwargs: object) -> object:
            bound = bind(signature, self, args, kwargs)
            if bound is not None:
                for text, check in checks:
                    if not check(self, *bound):
                        raise AssertionError(text)
            return fn(self, *args, **kwargs)

        return guarded

    ctx.report.phase("history")
    program.run()  # the history is what happened: preconditions judge only the proposed calls
    program.instrument(wrap)
    for unit, call in enumerate(calls):
        if unit not in ctx.skip:
            ctx.report.begin(unit, f"proposed call {unit}")
            ctx.report.unit(unit, _verdict(spec, program, guards, signatures, call))
    last = len(calls)  # the history judged as a part of its own: a runaway rule fails that part only
    if last not in ctx.skip and any(codes.values()):
        ctx.report.begin(last, "the history, judged against the preconditions")
        ctx.report.unit(last, _first_broken(spec, payload.get("history"), codes))
    return {}


def _first_broken(spec: Spec, source: object, codes: dict[str, list[tuple[str, types.CodeType]]]
                  ) -> dict[str, object]:
    """Where the history, run again on a fresh instance of the spec, first called an action whose rules did not
    hold (`line`, `action`, `rules`: those that did not, or raised); `{"line": None}` when it never did. Only
    the history's own calls are judged, not the calls a spec method makes."""
    program = Program(spec, source, "history", None)
    guards = {q: [(text, eval(code, program.globals)) for text, code in items] for q, items in codes.items()}
    found: dict[str, object] = {"line": None}
    depth = [0]

    def wrap(method: Method, fn: typing.Any, signature: inspect.Signature) -> typing.Any:
        checks = guards.get(method.qualname, [])

        def observed(self: object, *args: object, **kwargs: object) -> object:
            bound = bind(signature, self, args, kwargs)
            if found["line"] is None and depth[0] == 0 and bound is not None and checks:
                broken = [text for text, check in checks if not _holds(check, self, bound)]
                if broken:
                    found.update(line=program.body[program.position].lineno, action=method.qualname, rules=broken)
            depth[0] += 1
            try:
                return fn(self, *args, **kwargs)
            finally:
                depth[0] -= 1

        return observed

    program.instrument(wrap)
    try:
        program.run()
    except FATAL:
        raise
    except BaseException:  # it ran once already; what it may do differently now is not the history's verdict
        pass
    return found


def _holds(check: typing.Any, receiver: object, values: tuple[object, ...]) -> bool:
    """A rule that raises does not hold (the call's verdict says how it raised)."""
    try:
        return bool(check(receiver, *values))
    except FATAL:
        raise
    except BaseException:
        return False


def _precondition_codes(spec: Spec, preconditions: dict[str, typing.Any]
                        ) -> dict[str, list[tuple[str, types.CodeType]]]:
    codes: dict[str, list[tuple[str, types.CodeType]]] = {}
    for qname, expressions in preconditions.items():
        method = spec.methods.get(qname)
        if method is None or not isinstance(expressions, list):
            raise Failure({"kind": "program", "where": "preconditions", "index": None, "line": None,
                           "exc_type": "ValueError", "message": f"unknown action {clean(str(qname), 100)}"})
        items = []
        for expression in expressions:
            try:
                items.append((typing.cast(str, expression), compile_assertion(expression, method, "<pre>")))
            except FATAL:
                raise
            except BaseException as exc:
                name, message = describe(exc)
                raise Failure({"kind": "program", "where": "preconditions", "index": None, "line": None,
                               "exc_type": name, "message": f"{method.qualname}: {message}"}) from None
        codes[qname] = items
    return codes


def _verdict(spec: Spec, program: Program, guards: dict[str, list[tuple[str, typing.Any]]],
             signatures: dict[str, tuple[typing.Any, inspect.Signature]], call: object) -> dict[str, object]:
    if not isinstance(call, dict):
        return {"allowed": False, "violations": [], "error": "malformed call"}
    state, _ = program.copy_variables()
    target, name = str(call.get("target")), str(call.get("method"))
    if target not in state:
        error = f"NameError: name {clean(target, 100)!r} is not defined"
        return {"allowed": False, "violations": [], "error": error}
    receiver = state[target]
    qname = _action_of(spec, program, receiver, name)
    if qname is None or qname not in signatures:
        kind = clean(type(receiver).__name__, 100)
        return {"allowed": False, "violations": [], "error": f"unknown action {kind}.{clean(name, 100)}"}
    fn, signature = signatures[qname]
    args = tuple(tupled(a) for a in call.get("args") or [])
    kwargs = {str(k): tupled(v) for k, v in (call.get("kwargs") or {}).items()}
    try:
        bound = signature.bind(receiver, *args, **kwargs)
    except TypeError as exc:
        return {"allowed": False, "violations": [], "error": "TypeError: " + clean(str(exc))}
    bound.apply_defaults()
    values = tuple(bound.args[1:])
    violations, errors = [], []
    for text, check in guards.get(qname, []):
        try:
            if not check(receiver, *values):
                violations.append(text)
        except FATAL:
            raise
        except BaseException as exc:  # a rule that raises is a broken rule, never a plain "not allowed"
            exc_name, message = describe(exc)
            errors.append(f"precondition {clean(text, 200)!r} of {qname} raised {exc_name}: {message}")
    if violations or errors:
        return {"allowed": False, "violations": violations, "error": "; ".join(errors) or None}
    try:
        fn(receiver, *args, **kwargs)
    except FATAL:
        raise
    except BaseException as exc:
        exc_name, message = describe(exc)
        return {"allowed": False, "violations": [], "error": f"{exc_name}: {message}"}
    return {"allowed": True, "violations": [], "error": None}


def _action_of(spec: Spec, program: Program, receiver: object, name: str) -> str | None:
    classes = {id(program.base.get(c)): c for c in spec.classes}
    for cls in type(receiver).__mro__:
        if id(cls) in classes and name in cls.__dict__:
            return f"{classes[id(cls)]}.{name}"
    return None


# ------------------------------------------------------------------------------------------ the child

"""Running the spec and a program inside the child: a fresh spec namespace per program, observed step by
step, with the method calls it makes recorded or guarded.

Everything here runs after ``boundary.confine``; the restricted builtins and the output cap are
conveniences that turn forbidden operations into readable errors, not protections.
"""

from __future__ import annotations

import ast
import builtins
import collections
import copy
import dataclasses
import functools
import inspect
import io
import sys
import types
import typing

from precond.programs import Method, Purity, main_body, read_methods
from precond.programs.lines import LINE_BREAKS, line_statements, source_segments

from .framing import Reporter
from .values import FATAL, Failure, OutputLimit, clean, describe

# Builtins that let code escape the restricted namespace or wait for a human.
_REMOVED_BUILTINS = ("open", "exec", "eval", "compile", "input", "breakpoint", "help", "exit", "quit",
                     "globals", "locals", "vars", "memoryview", "__loader__", "__spec__")


class CappedWriter(io.TextIOBase):
    """Replacement for sys.stdout/stderr: output is discarded, but its volume is limited."""

    def __init__(self, budget: list[int]) -> None:
        self._budget = budget
        self.buffer = _CappedBytes(budget)

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        if not isinstance(text, str):
            raise TypeError("write() argument must be str")
        _spend(self._budget, len(text))
        return len(text)


class _CappedBytes(io.RawIOBase):
    def __init__(self, budget: list[int]) -> None:
        self._budget = budget

    def writable(self) -> bool:
        return True

    def write(self, data: typing.Any) -> int:
        size = len(memoryview(data).cast("B"))
        _spend(self._budget, size)
        return size


def _spend(budget: list[int], size: int) -> None:
    budget[0] -= size
    if budget[0] < 0:
        raise OutputLimit("output limit exceeded")



def restricted_builtins(allowed_imports: frozenset[str]) -> dict[str, object]:
    """Builtins for untrusted code: no file/eval/introspection helpers, imports from a whitelist only."""
    real_import = builtins.__import__

    def guarded_import(name: str, globals: object = None, locals: object = None,
                       fromlist: object = (), level: int = 0) -> types.ModuleType:
        if level != 0 or not isinstance(name, str) or name.partition(".")[0] not in allowed_imports:
            raise ImportError(f"import of {name!r} is not allowed")
        return real_import(name, globals, locals, fromlist, level)  # type: ignore[arg-type]

    table = dict(vars(builtins))
    for name in _REMOVED_BUILTINS:
        table.pop(name, None)
    table["__import__"] = guarded_import
    return table


def quiet_output(limit: int) -> list[int]:
    """stdout/stderr of untrusted code are discarded, but their volume counts against `limit`."""
    budget = [limit]
    sys.stdout = CappedWriter(budget)
    sys.stderr = CappedWriter(budget)
    return budget


def stack_depth() -> int:
    frame, depth = sys._getframe(), 0
    while frame is not None:
        frame, depth = frame.f_back, depth + 1  # type: ignore[assignment]
    return depth + 50


UNDO_LOG: list[tuple[dict[object, object], object]] = []
UNDO_ON = [False]
_DEFAULTDICT = collections.defaultdict


class UndoDefaultDict(_DEFAULTDICT):  # type: ignore[type-arg]
    """defaultdict whose reads may insert keys: while a candidate runs, insertions are logged and undone,
    so that `d[k]` in one candidate cannot change what `k in d` means for another."""

    def __missing__(self, key: object) -> object:
        value = _DEFAULTDICT.__missing__(self, key)
        if UNDO_ON[0]:
            UNDO_LOG.append((self, key))
        return value


def rollback() -> None:
    for table, key in reversed(UNDO_LOG):
        dict.pop(table, key, None)
    UNDO_LOG.clear()


def fail(where: str, index: int | None, line: int | None, exc: BaseException) -> Failure:
    if isinstance(exc, Failure):
        return exc
    if isinstance(exc, RecursionError):
        message = f"{where}: maximum recursion depth"
        return Failure({"kind": "limit", "limit": "recursion", "message": message})
    name, message = describe(exc)
    return Failure({"kind": "program", "where": where, "index": index, "line": line,
                    "exc_type": name, "message": message})


def error_line(exc: BaseException, filename: str) -> int | None:
    """Line of the deepest frame of `filename` in the traceback: the statement of that program that failed."""
    if isinstance(exc, SyntaxError) and exc.filename == filename:
        return exc.lineno
    line = None
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == filename:
            line = tb.tb_lineno
        tb = tb.tb_next
    return line


def parse(source: object, filename: str, where: str, index: int | None) -> ast.Module:
    if not isinstance(source, str):
        raise Failure({"kind": "bad_request", "message": f"{where} must be a string"})
    try:
        return ast.parse(source, filename)
    except FATAL:
        raise
    except BaseException as exc:
        raise fail(where, index, error_line(exc, filename), exc) from None


COMPILED_MAX = 4096
"""Compiled programs, statements and rules a child keeps; only a warm child (one scope's, see
`sandbox.child.server`) ever sees a second request, so only there are they reused."""
_COMPILED: dict[object, typing.Any] = {}


def compiled(key: object, build: typing.Callable[[], typing.Any]) -> typing.Any:
    """`build()`, remembered under `key` (text in, code out: nothing of a run is kept)."""
    found = _COMPILED.get(key)
    if found is None:
        if len(_COMPILED) >= COMPILED_MAX:
            _COMPILED.clear()
        found = _COMPILED[key] = build()
    return found


class Spec:
    """The spec program: compiled once per request (per source text in a warm child), executed afresh for every
    program that uses it."""

    FILE = "<spec>"

    def __init__(self, source: object, builtins_table: dict[str, object]) -> None:
        self.builtins = builtins_table
        read: tuple[ast.Module, types.CodeType, list[str], dict[str, Method]] = (
            compiled(("spec", source), lambda: self._read(source)) if isinstance(source, str) else self._read(source))
        self._tree, self.code, self.classes, self.methods = read

    @classmethod
    def _read(cls, source: object) -> tuple[ast.Module, types.CodeType, list[str], dict[str, Method]]:
        tree = parse(source, cls.FILE, "spec", None)
        code = compile(tree, cls.FILE, "exec")
        return tree, code, [n.name for n in tree.body if isinstance(n, ast.ClassDef)], read_methods(tree)

    @functools.cached_property
    def purity(self) -> Purity:
        return Purity(self._tree)

    def instantiate(self) -> dict[str, object]:
        namespace: dict[str, object] = {"__builtins__": self.builtins, "__name__": "spec"}
        try:
            exec(self.code, namespace)
        except FATAL:
            raise
        except BaseException as exc:
            raise fail("spec", None, error_line(exc, self.FILE), exc) from None
        return namespace

    def live_method(self, namespace: dict[str, object], method: Method) -> tuple[type, typing.Any] | None:
        cls = namespace.get(method.cls)
        if not isinstance(cls, type):
            return None
        fn = cls.__dict__.get(method.name)
        return (cls, fn) if isinstance(fn, types.FunctionType) else None



def _literal(node: ast.AST) -> bool:
    if isinstance(node, ast.Constant):
        return True
    if isinstance(node, (ast.Tuple, ast.List)):
        return all(_literal(e) for e in node.elts)
    return isinstance(node, ast.UnaryOp) and isinstance(node.operand, ast.Constant)


def _direct_call(stmt: ast.stmt) -> bool:
    """`name.method(<literals>)`: the state at call time equals the state before the statement."""
    if not (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Call)):
        return False
    call = stmt.value
    return (isinstance(call.func, ast.Attribute) and isinstance(call.func.value, ast.Name)
            and all(_literal(a) for a in call.args) and all(_literal(k.value) for k in call.keywords))


@dataclasses.dataclass
class Occurrence:
    demo: int
    position: int
    line: int
    args: tuple[object, ...]
    state: object


class Program:
    """One demonstration (or history) run on a fresh instance of the spec, observed position by position."""

    FILE = "<program>"

    def __init__(self, spec: Spec, source: object, where: str, index: int | None,
                 report: Reporter | None = None) -> None:
        self.spec, self.where, self.index = spec, where, index
        self.lines = LINE_BREAKS.split(source) if isinstance(source, str) else []  # what `lineno` counts
        # a history is read line by line, each line once per warm child (a dialog's grows by a line a turn)
        read = line_statements(self.lines, compiled) if where == "history" and self.lines else None
        tree = parse(source, self.FILE, where, index) if read is None else ast.Module(body=read, type_ignores=[])
        self.source = typing.cast(str, source)
        self.body = main_body(tree)
        label = where if index is None else f"{where}s[{index}]"
        if report is not None:  # a limit hit while the spec's own top level runs is the spec's, not the program's
            report.phase(f"the spec's top level (run anew for {label})")
        self.globals = spec.instantiate()
        if report is not None:
            report.phase(label)
        self.base = dict(self.globals)
        self.position = -1
        self.calls_in_statement = 0
        self.memo: dict[int, object] | None = None
        self.snapshots: list[dict[str, object]] = []

    def positions(self) -> list[list[object]]:
        return [[s.lineno, clean(text or "", 2000)]
                for s, text in zip(self.body, source_segments(self.source, self.body), strict=True)]

    def variables(self) -> dict[str, object]:
        base = self.base
        return {k: v for k, v in self.globals.items()
                if (k not in base or base[k] is not v) and not isinstance(v, types.ModuleType)}

    def run(self, snapshot: bool = False) -> None:
        for position, stmt in enumerate(self.body):
            self.position, self.calls_in_statement = position, 0
            self.memo = None
            if snapshot:
                self.snapshots.append(self._snapshot(direct=_direct_call(stmt)))
            code = self._code(stmt)
            try:
                exec(code, self.globals)
            except FATAL:
                raise
            except BaseException as exc:
                raise fail(self.where, self.index, error_line(exc, self.FILE) or stmt.lineno, exc) from None
        self.memo = None

    def _code(self, stmt: ast.stmt) -> types.CodeType:
        """A statement's code; a one-line statement's by its place and text (a dialog's history is re-sent
        with one more turn each time, its earlier lines unchanged)."""
        def build() -> types.CodeType:
            return compile(ast.Module(body=[stmt], type_ignores=[]), self.FILE, "exec")

        if stmt.end_lineno != stmt.lineno or not 0 < stmt.lineno <= len(self.lines):
            return build()
        key = ("statement", stmt.lineno, stmt.col_offset, stmt.end_col_offset, self.lines[stmt.lineno - 1])
        return typing.cast(types.CodeType, compiled(key, build))

    def copy_variables(self) -> tuple[dict[str, object], dict[int, object]]:
        """Deep copy of the variables that keeps identity sharing; what cannot be copied is left out."""
        variables, memo = self.variables(), typing.cast(dict[int, object], {})
        try:
            return copy.deepcopy(variables, memo), memo
        except FATAL:
            raise
        except BaseException:
            memo = {}
            copied = {}
            for name, value in variables.items():
                try:
                    copied[name] = copy.deepcopy(value, memo)
                except FATAL:
                    raise
                except BaseException:
                    continue
            return copied, memo

    def _snapshot(self, direct: bool) -> dict[str, object]:
        copied, memo = self.copy_variables()
        self.memo = memo if direct else None
        return copied

    def receiver_state(self, receiver: object) -> object:
        """State an assertion in the called method would see: the position snapshot when that is exact,
        else a copy taken now."""
        if self.calls_in_statement == 0 and self.memo is not None and id(receiver) in self.memo:
            return self.memo[id(receiver)]
        try:
            return copy.deepcopy(receiver)
        except FATAL:
            raise
        except BaseException:
            return None

    def call_line(self) -> int:
        """Line of the program that made the current call (inside loops too), for messages."""
        frame = sys._getframe(2)
        while frame is not None and frame.f_code.co_filename != self.FILE:
            frame = frame.f_back  # type: ignore[assignment]
        if frame is not None:
            return frame.f_lineno
        return self.body[self.position].lineno if 0 <= self.position < len(self.body) else 0

    def instrument(self, wrap: typing.Callable[[Method, typing.Any, inspect.Signature], typing.Any]
                   ) -> typing.Callable[[], None]:
        """Replace spec methods on this program's classes; returns the function that puts them back."""
        originals: list[tuple[type, str, object]] = []
        for method in self.spec.methods.values():
            live = self.spec.live_method(self.base, method)
            if live is None:
                continue
            cls, fn = live
            try:
                signature = signature_of(fn)
            except (TypeError, ValueError):
                continue
            originals.append((cls, method.name, fn))
            type.__setattr__(cls, method.name, wrap(method, fn, signature))

        def restore() -> None:
            for cls, name, fn in originals:
                type.__setattr__(cls, name, fn)

        return restore


def signature_of(fn: types.FunctionType) -> inspect.Signature:
    """`inspect.signature(fn)`; remembered by code object for a function whose signature is its code's alone
    (no defaults, no attributes such as `__signature__` or `__wrapped__`), kept without its annotations (objects
    of the request that made it). The spec's methods are made afresh by every request, from the same code:
    computing 24 signatures each time was half of a check's work in a warm child."""
    if fn.__defaults__ is not None or fn.__kwdefaults__ is not None or fn.__dict__:
        return inspect.signature(fn)

    def bare() -> inspect.Signature:
        signature = inspect.signature(fn)
        parameters = [p.replace(annotation=inspect.Parameter.empty) for p in signature.parameters.values()]
        return signature.replace(parameters=parameters, return_annotation=inspect.Signature.empty)

    return typing.cast(inspect.Signature, compiled(("signature", fn.__code__), bare))


def bind(signature: inspect.Signature, receiver: object, args: tuple[object, ...],
         kwargs: dict[str, object]) -> tuple[object, ...] | None:
    try:
        bound = signature.bind(receiver, *args, **kwargs)
    except TypeError:
        return None
    bound.apply_defaults()
    return tuple(bound.args[1:])


def recorder(program: Program, on_call: typing.Callable[[Method, object, tuple[object, ...]], None]
             ) -> typing.Callable[[Method, typing.Any, inspect.Signature], typing.Any]:
    def wrap(method: Method, fn: typing.Any, signature: inspect.Signature) -> typing.Any:
        def wrapper(self: object, *args: object, **kwargs: object) -> object:
            bound = bind(signature, self, args, kwargs)
            if bound is not None:
                on_call(method, self, bound)
            program.calls_in_statement += 1
            return fn(self, *args, **kwargs)

        return wrapper

    return wrap


@dataclasses.dataclass
class Context:
    """What a job gets besides its payload: the builtins of untrusted code, the stream to the server, and
    the units an earlier child of the same call already settled (skipped here)."""

    builtins: dict[str, object]
    report: Reporter
    skip: frozenset[int] = frozenset()


def load(payload: dict[str, typing.Any], ctx: Context) -> tuple[Spec, list[object]]:
    ctx.report.phase("spec")
    spec = Spec(payload.get("spec"), ctx.builtins)
    demos = payload.get("demonstrations")
    if not isinstance(demos, list):
        raise Failure({"kind": "bad_request", "message": "demonstrations must be a list"})
    return spec, demos

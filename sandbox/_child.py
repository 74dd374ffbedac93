"""Fork server that runs untrusted programs; the only place where untrusted code is ever executed.

Started as ``python -I _child.py REQUEST_FD RESPONSE_FD CONFIG_JSON`` by ``sandbox.pool``. It must stay a
single stdlib-only script: ``-I`` keeps the project, site-packages and environment out of the interpreter
that untrusted code can reach. The server imports everything once (warm), then forks a fresh child per
request, so every request sees a pristine interpreter and a child that hit a limit is never reused.

Wire format, both directions JSON (never pickle), on dedicated pipes (never fd 1/2):
request line ``{"op", "payload"}`` (limits are fixed per server,
from CONFIG_JSON); reply a header line ``{"status": "ok", "size": N}`` followed by N
bytes of child result and a newline, or a header ``{"status": "limit"|"crash", ...}`` alone.
"""

from __future__ import annotations

import abc
import ast
import builtins
import collections
import contextlib
import copy
import ctypes
import dataclasses
import enum
import functools
import gc
import inspect
import io
import itertools
import json
import math
import os
import re
import resource
import select
import shutil
import signal
import string
import sys
import tempfile
import time
import types
import typing
import warnings

# Referenced so that the whitelisted modules are loaded before the audit hook forbids new imports.
_PRELOADED = (abc, copy, dataclasses, enum, functools, itertools, math, re, string, typing)

NOBODY = 65534
CLONE_NEWUSER = 0x10000000
CLONE_NEWNET = 0x40000000
PR_SET_PDEATHSIG = 1
PR_SET_NO_NEW_PRIVS = 38
REQUEST_FD = 3
RESULT_FD = 4
SPARE_FD = 900
LENGTH_CHARS = 16
MESSAGE_CHARS = 500
CHUNK = 1 << 20

# Builtins that let code escape the restricted namespace or wait for a human.
_REMOVED_BUILTINS = ("open", "exec", "eval", "compile", "input", "breakpoint", "help", "exit", "quit",
                     "globals", "locals", "vars", "memoryview", "__loader__", "__spec__")

# Events that never have a legitimate use in untrusted code (prefix match on "name.").
_BLOCKED_EVENTS = frozenset({
    "os.system", "os.exec", "os.posix_spawn", "os.spawn", "os.fork", "os.forkpty", "os.kill", "os.killpg",
    "os.startfile", "subprocess.Popen", "pty.spawn", "sys.addaudithook", "resource.setrlimit",
    "resource.prlimit", "builtins.input", "os.chroot", "os.setuid", "os.setgid",
})
_BLOCKED_PREFIXES = ("socket.", "ctypes.", "_posixsubprocess.", "mmap.", "webbrowser.", "ftplib.", "http.",
                     "smtplib.", "urllib.", "imaplib.", "poplib.", "telnetlib.", "nntplib.")
# Events whose leading arguments are paths that must stay inside the private temp dir.
_PATH_EVENTS = {
    "open": 1, "os.listdir": 1, "os.scandir": 1, "os.chdir": 1, "os.mkdir": 1, "os.remove": 1,
    "os.rmdir": 1, "os.rename": 2, "os.replace": 2, "os.symlink": 2, "os.link": 2, "os.truncate": 1,
    "os.utime": 1, "os.chmod": 1, "os.chown": 1, "os.chflags": 1, "os.lchflags": 1, "os.setxattr": 1,
    "os.getxattr": 1, "os.listxattr": 1, "os.removexattr": 1, "shutil.copyfile": 2, "shutil.copymode": 2,
    "shutil.copystat": 2, "shutil.copytree": 2, "shutil.chown": 1, "shutil.move": 2, "shutil.rmtree": 1,
    "shutil.make_archive": 1, "shutil.unpack_archive": 2, "glob.glob": 1, "tempfile.mkstemp": 1,
    "tempfile.mkdtemp": 1,
}

# Static purity analysis: what a call may do to the state. Unknown callees count as mutating.
_MUTATOR_NAMES = frozenset({
    "append", "add", "update", "pop", "popitem", "clear", "remove", "discard", "setdefault", "extend",
    "insert", "sort", "reverse", "appendleft", "extendleft", "popleft", "rotate", "send", "throw", "close",
    "write", "difference_update", "intersection_update", "symmetric_difference_update", "subtract",
})
_PURE_METHODS = frozenset({
    "get", "keys", "values", "items", "count", "index", "startswith", "endswith", "lower", "upper",
    "strip", "lstrip", "rstrip", "split", "rsplit", "find", "rfind", "join", "replace", "isdigit",
    "isalpha", "isalnum", "isspace", "islower", "isupper", "title", "capitalize", "casefold", "format",
    "issubset", "issuperset", "isdisjoint", "union", "intersection", "difference",
    "symmetric_difference", "copy", "most_common", "elements", "partition", "rpartition", "zfill",
    "isnumeric", "isdecimal", "isidentifier", "removeprefix", "removesuffix", "splitlines",
})
_PURE_FUNCTIONS = frozenset({
    "len", "any", "all", "isinstance", "issubclass", "sorted", "min", "max", "sum", "abs", "bool", "int",
    "str", "float", "list", "tuple", "set", "frozenset", "dict", "range", "enumerate", "zip", "reversed",
    "round", "repr", "hash", "callable", "type", "ord", "chr", "divmod", "pow", "format", "map", "filter",
})


class Failure(Exception):
    """A structured error for the caller, as opposed to a bug in this script."""

    def __init__(self, info: dict[str, object]) -> None:
        super().__init__(info.get("message"))
        self.info = info


class OutputLimit(BaseException):
    """Untrusted output went over its budget; BaseException so that `except Exception` cannot swallow it."""


_FATAL = (MemoryError, OutputLimit)


# ---------------------------------------------------------------------------------------------- text


def clean(text: str, limit: int = MESSAGE_CHARS) -> str:
    """Make untrusted text safe for JSON/HTTP: no lone surrogates, bounded length."""
    safe = text.encode("utf-8", "backslashreplace").decode("utf-8")
    return safe if len(safe) <= limit else safe[: limit - 3] + "..."


def describe(exc: BaseException) -> tuple[str, str]:
    """Type name and message of an untrusted exception; a `__str__` that raises gives no message."""
    name = clean(type(exc).__name__, 100)
    try:
        message = str(exc)
    except _FATAL:
        raise
    except BaseException:
        message = ""
    if not isinstance(message, str):
        message = ""
    return name, clean(message)


def jsonable(value: object) -> object:
    """Argument values as JSON values; anything else travels as its (clean) repr."""
    if value is None or isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, str):
        return value
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    try:
        return clean(repr(value), 200)
    except _FATAL:
        raise
    except BaseException:
        return clean(type(value).__name__, 100)


def tupled(value: object) -> object:
    """JSON arrays back into tuples, the form argument values have at the caller."""
    if isinstance(value, list):
        return tuple(tupled(v) for v in value)
    return value


# --------------------------------------------------------------------------------- isolation: server


def isolate_network(libc: ctypes.CDLL, was_root: bool) -> str | None:
    """New empty network namespace; returns why not when the OS refuses (caller logs a warning)."""
    flags = CLONE_NEWNET if was_root else CLONE_NEWUSER | CLONE_NEWNET
    if libc.unshare(flags) == 0:
        return None
    return f"unshare failed: {os.strerror(ctypes.get_errno())}"


# ---------------------------------------------------------------------------------- isolation: child


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


def make_audit_hook(root: str) -> typing.Callable[[str, tuple[object, ...]], None]:
    """Audit hook: the boundary that still holds when untrusted code reaches real modules by introspection."""
    prefix = root.rstrip("/") + "/"
    loaded = sys.modules

    def inside(path: object) -> bool:
        if isinstance(path, bytes):
            path = os.fsdecode(path)
        if not isinstance(path, str):
            return False
        real = os.path.realpath(path)
        return real == root or real.startswith(prefix)

    def hook(event: str, args: tuple[object, ...]) -> None:
        if event in _BLOCKED_EVENTS or event.startswith(_BLOCKED_PREFIXES):
            raise PermissionError(f"sandbox: {event} is not allowed")
        if event == "import":
            if args and args[0] not in loaded:
                raise PermissionError(f"sandbox: import of {args[0]!r} is not allowed")
            return
        count = _PATH_EVENTS.get(event)
        if count is not None:
            for path in args[:count]:
                if path is not None and not inside(path):
                    raise PermissionError(f"sandbox: {event} outside the working directory is not allowed")

    return hook


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


def confine(limits: dict[str, typing.Any], workdir: str, was_root: bool, server_pid: int) -> list[int]:
    """Everything the forked child does to itself before untrusted code runs; returns the output budget."""
    os.setpgid(0, 0)
    devnull = os.open(os.devnull, os.O_RDWR)
    for fd in (0, 1, 2):
        os.dup2(devnull, fd)
    os.closerange(RESULT_FD + 1, 1 << 16)
    os.chdir(workdir)
    cpu = int(limits["cpu_s"])
    memory = int(limits["memory_mb"]) << 20
    for which, soft, hard in (
        (resource.RLIMIT_CPU, cpu, cpu + 1),
        (resource.RLIMIT_AS, memory, memory),
        (resource.RLIMIT_NOFILE, int(limits["open_files"]), int(limits["open_files"])),
        (resource.RLIMIT_NPROC, 0, 0),
        (resource.RLIMIT_CORE, 0, 0),
        (resource.RLIMIT_FSIZE, int(limits["output_bytes"]), int(limits["output_bytes"])),
    ):
        resource.setrlimit(which, (soft, hard))
    if was_root:
        os.setgroups([])
        os.setgid(NOBODY)
        os.setuid(NOBODY)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != server_pid:
        os._exit(1)
    budget = [int(limits["output_bytes"])]
    sys.stdout = CappedWriter(budget)
    sys.stderr = CappedWriter(budget)
    warnings.simplefilter("ignore")
    gc.disable()
    sys.setrecursionlimit(_depth() + int(limits["recursion"]))
    sys.addaudithook(make_audit_hook(os.path.realpath(workdir)))
    collections.defaultdict = UndoDefaultDict  # type: ignore[misc]
    return budget


def _depth() -> int:
    frame, depth = sys._getframe(), 0
    while frame is not None:
        frame, depth = frame.f_back, depth + 1  # type: ignore[assignment]
    return depth + 50


# ------------------------------------------------------------------------------- isolation of candidates

_UNDO: list[tuple[dict[object, object], object]] = []
_UNDO_ON = [False]


_DEFAULTDICT = collections.defaultdict


class UndoDefaultDict(_DEFAULTDICT):  # type: ignore[type-arg]
    """defaultdict whose reads may insert keys: while a candidate runs, insertions are logged and undone,
    so that `d[k]` in one candidate cannot change what `k in d` means for another."""

    def __missing__(self, key: object) -> object:
        value = _DEFAULTDICT.__missing__(self, key)
        if _UNDO_ON[0]:
            _UNDO.append((self, key))
        return value


def rollback() -> None:
    for table, key in reversed(_UNDO):
        dict.pop(table, key, None)
    _UNDO.clear()


class Purity:
    """Static guess of which spec functions may mutate state; a wrong 'pure' would break isolation, so any
    callee it does not know counts as impure."""

    def __init__(self, tree: ast.Module) -> None:
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        self.known = {f.name for f in functions}
        self.impure: set[str] = {f.name for f in functions if self._locally_impure(f)}
        calls = {id(f): self._callees(f) for f in functions}
        changed = True
        while changed:
            changed = False
            for f in functions:
                if f.name not in self.impure and calls[id(f)] & self.impure:
                    self.impure.add(f.name)
                    changed = True
        self.everything_slow = any(
            f.name in self.impure and (f.decorator_list or (f.name.startswith("__") and f.name != "__init__"))
            for f in functions
        )

    def expression_is_pure(self, node: ast.AST) -> bool:
        return not self.everything_slow and not self._locally_impure(node) and not (
            self._callees(node) & self.impure
        )

    def _callees(self, node: ast.AST) -> set[str]:
        names: set[str] = set()
        for sub in ast.walk(node):
            if isinstance(sub, ast.Call):
                if isinstance(sub.func, ast.Name):
                    names.add(sub.func.id)
                elif isinstance(sub.func, ast.Attribute):
                    names.add(sub.func.attr)
        return names

    def _locally_impure(self, node: ast.AST) -> bool:
        for sub in ast.walk(node):
            if isinstance(sub, (ast.AugAssign, ast.Delete, ast.Global, ast.Nonlocal, ast.Yield,
                                ast.YieldFrom, ast.Await)):
                return True
            if isinstance(sub, (ast.Assign, ast.AnnAssign)):
                targets = sub.targets if isinstance(sub, ast.Assign) else [sub.target]
                if any(isinstance(t, (ast.Attribute, ast.Subscript)) for tg in targets for t in ast.walk(tg)):
                    return True
            if isinstance(sub, ast.Attribute) and sub.attr in _MUTATOR_NAMES:
                return True
            if isinstance(sub, ast.Call) and not self._call_known(sub):
                return True
        return False

    def _call_known(self, call: ast.Call) -> bool:
        if isinstance(call.func, ast.Name):
            return call.func.id in _PURE_FUNCTIONS or call.func.id in self.known
        if isinstance(call.func, ast.Attribute):
            return call.func.attr in _PURE_METHODS or call.func.attr in self.known
        return False


# ------------------------------------------------------------------------------------------- programs


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
    except _FATAL:
        raise
    except BaseException as exc:
        raise fail(where, index, error_line(exc, filename), exc) from None


@dataclasses.dataclass
class Method:
    qname: str
    cls: str
    name: str
    params: list[str]
    positional: list[str]
    vararg: str | None
    stub: bool


def _is_stub(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return all(
        isinstance(s, ast.Pass)
        or (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant)
            and (s.value.value is Ellipsis or isinstance(s.value.value, str)))
        for s in node.body
    )


def _method(cls: str, node: ast.FunctionDef | ast.AsyncFunctionDef) -> Method:
    a = node.args
    positional = [x.arg for x in a.posonlyargs + a.args][1:]
    params = positional + ([f"*{a.vararg.arg}"] if a.vararg else []) + [x.arg for x in a.kwonlyargs]
    params += [f"**{a.kwarg.arg}"] if a.kwarg else []
    return Method(f"{cls}.{node.name}", cls, node.name, params, positional,
                  a.vararg.arg if a.vararg else None, _is_stub(node))


class Spec:
    """The spec program: compiled once per request, executed afresh for every program that uses it."""

    FILE = "<spec>"

    def __init__(self, source: object, builtins_table: dict[str, object]) -> None:
        tree = parse(source, self.FILE, "spec", None)
        self.builtins = builtins_table
        self.code = compile(tree, self.FILE, "exec")
        self.classes = [n.name for n in tree.body if isinstance(n, ast.ClassDef)]
        self.methods: dict[str, Method] = {}
        for node in tree.body:
            if isinstance(node, ast.ClassDef):
                for item in node.body:
                    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and not (
                        item.name.startswith("__") and item.name.endswith("__")
                    ):
                        method = _method(node.name, item)
                        self.methods[method.qname] = method
        self._tree = tree

    @functools.cached_property
    def purity(self) -> Purity:
        return Purity(self._tree)

    def instantiate(self) -> dict[str, object]:
        namespace: dict[str, object] = {"__builtins__": self.builtins, "__name__": "spec"}
        try:
            exec(self.code, namespace)
        except _FATAL:
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


def main_body(tree: ast.Module) -> list[ast.stmt]:
    """SGD style: the module body. ALFWorld style: the body of its single function (plus its call)."""
    body = tree.body
    if body and isinstance(body[0], ast.FunctionDef) and len(body) <= 2:
        fn = body[0]
        if len(body) == 1 or (
            isinstance(body[1], ast.Expr) and isinstance(body[1].value, ast.Call)
            and isinstance(body[1].value.func, ast.Name) and body[1].value.func.id == fn.name
            and not body[1].value.args
        ):
            return fn.body
    return body


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

    def __init__(self, spec: Spec, source: object, where: str, index: int | None) -> None:
        self.spec, self.where, self.index = spec, where, index
        tree = parse(source, self.FILE, where, index)
        self.source = typing.cast(str, source)
        self.body = main_body(tree)
        self.globals = spec.instantiate()
        self.base = dict(self.globals)
        self.position = -1
        self.calls_in_statement = 0
        self.memo: dict[int, object] | None = None
        self.snapshots: list[dict[str, object]] = []

    def positions(self) -> list[list[object]]:
        return [[s.lineno, clean(ast.get_source_segment(self.source, s) or "", 2000)] for s in self.body]

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
            code = compile(ast.Module(body=[stmt], type_ignores=[]), self.FILE, "exec")
            try:
                exec(code, self.globals)
            except _FATAL:
                raise
            except BaseException as exc:
                raise fail(self.where, self.index, error_line(exc, self.FILE) or stmt.lineno, exc) from None
        self.memo = None

    def copy_variables(self) -> tuple[dict[str, object], dict[int, object]]:
        """Deep copy of the variables that keeps identity sharing; what cannot be copied is left out."""
        variables, memo = self.variables(), typing.cast(dict[int, object], {})
        try:
            return copy.deepcopy(variables, memo), memo
        except _FATAL:
            raise
        except BaseException:
            memo = {}
            copied = {}
            for name, value in variables.items():
                try:
                    copied[name] = copy.deepcopy(value, memo)
                except _FATAL:
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
        except _FATAL:
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
                signature = inspect.signature(fn)
            except (TypeError, ValueError):
                continue
            originals.append((cls, method.name, fn))
            type.__setattr__(cls, method.name, wrap(method, fn, signature))

        def restore() -> None:
            for cls, name, fn in originals:
                type.__setattr__(cls, name, fn)

        return restore


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


# ---------------------------------------------------------------------------------------------- trace


def load(payload: dict[str, typing.Any], ctx: Context) -> tuple[Spec, list[object]]:
    spec = Spec(payload.get("spec"), ctx.builtins)
    demos = payload.get("demonstrations")
    if not isinstance(demos, list):
        raise Failure({"kind": "bad_request", "message": "demonstrations must be a list"})
    return spec, demos


def job_trace(payload: dict[str, typing.Any], ctx: Context) -> dict[str, object]:
    spec, demos = load(payload, ctx)
    occurrences: dict[str, list[list[object]]] = {q: [] for q in spec.methods}
    seen: dict[str, dict[str, object]] = {q: {} for q in spec.methods}
    positions = []
    for index, source in enumerate(demos):
        program = Program(spec, source, "demonstration", index)

        def on_call(method: Method, receiver: object, args: tuple[object, ...], p: Program = program) -> None:
            values = jsonable(args)
            occurrences[method.qname].append([p.index, p.position, values])
            seen[method.qname].setdefault(json.dumps(values, sort_keys=True), values)

        program.instrument(recorder(program, on_call))
        program.run()
        positions.append(program.positions())
    actions = {
        q: {"params": m.params, "stub": m.stub, "occurrences": occurrences[q],
            "arg_values": list(seen[q].values())}
        for q, m in spec.methods.items()
    }
    return {"positions": positions, "actions": actions}


# ------------------------------------------------------------------------------------------- evaluate


def compile_assertion(expression: object, method: Method, filename: str) -> types.CodeType:
    """`lambda self, <params>: (<expression>)`, built as an AST so that no text is spliced."""
    if not isinstance(expression, str):
        raise SyntaxError("not a string")
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
    _UNDO_ON[0] = True
    try:
        return bool(fn(state if pure else copy.deepcopy(state), *args))
    finally:
        _UNDO_ON[0] = False
        if _UNDO:
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
        except _FATAL:
            raise
        except BaseException:
            pass
    bits.reverse()
    return format(int(bits or b"0", 2), "x")


def first_violation(candidate: Candidate, occurrences: list[Occurrence]) -> str | None:
    for occ in occurrences:
        where = f"demonstration {occ.demo}, line {occ.line}, args {clean(repr(jsonable(occ.args)), 200)}"
        if occ.state is None:
            return f"{where}: the state could not be copied"
        try:
            if not holds(candidate.functions[occ.demo], occ.state, occ.args, candidate.pure):
                return f"{where}: assertion fails"
        except _FATAL:
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
    programs = [_observe(spec, i, source, wanted, occurrences) for i, source in enumerate(demos)]
    results: dict[str, object] = {}
    points_out: dict[str, object] = {}
    for qname, expressions in candidates.items():
        method = spec.methods.get(qname)
        if method is None or not isinstance(expressions, list):
            results[qname] = [{"status": "rejected", "reason": f"unknown action {clean(qname, 100)}"}
                              for _ in (expressions if isinstance(expressions, list) else [])]
            continue
        if qname in custom:
            points = _custom_points(programs, method, custom[qname])
        else:
            values = _default_values(method, occurrences[qname])
            where = _default_positions(programs, method)
            points_out[qname] = {"positions": where, "arg_values": [jsonable(v) for v in values]}
            points = [(d, programs[d].self_at(p, method), v) for d, p in where for v in values]
        results[qname] = [_judge(spec, programs, method, e, occurrences[qname], points) for e in expressions]
    return {"points": points_out, "results": results}


def _observe(spec: Spec, index: int, source: object, wanted: set[str],
             occurrences: dict[str, list[Occurrence]]) -> Observed:
    program = Program(spec, source, "demonstration", index)

    def on_call(method: Method, receiver: object, args: tuple[object, ...]) -> None:
        if method.qname in wanted:
            state = program.receiver_state(receiver)
            occurrences[method.qname].append(
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
        raise Failure({"kind": "bad_request", "message": f"points of {method.qname} must be a list"})
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
    except _FATAL:
        raise
    except BaseException as exc:
        name, message = describe(exc)
        return {"status": "rejected", "reason": f"{name}: {message}"}
    tree = ast.parse(typing.cast(str, expression), mode="eval")
    functions = [eval(code, obs.globals) for obs in programs]
    candidate = Candidate(spec.purity.expression_is_pure(tree), functions)
    violation = first_violation(candidate, occurrences)
    return {"status": "valid" if violation is None else "invalid", "reason": violation,
            "satisfied": satisfied(candidate, points)}


# ---------------------------------------------------------------------------------------------- check


def job_check(payload: dict[str, typing.Any], ctx: Context) -> dict[str, object]:
    spec = Spec(payload.get("spec"), ctx.builtins)
    preconditions = payload.get("preconditions")
    calls = payload.get("calls")
    if not isinstance(preconditions, dict) or not isinstance(calls, list):
        raise Failure({"kind": "bad_request", "message": "preconditions must be an object, calls a list"})
    codes = _precondition_codes(spec, preconditions)
    program = Program(spec, payload.get("history"), "history", None)
    guards: dict[str, list[tuple[str, typing.Any]]] = {
        q: [(text, eval(code, program.globals)) for text, code in items] for q, items in codes.items()
    }
    signatures: dict[str, tuple[typing.Any, inspect.Signature]] = {}

    def wrap(method: Method, fn: typing.Any, signature: inspect.Signature) -> typing.Any:
        signatures[method.qname] = (fn, signature)
        checks = guards.get(method.qname, [])

        def guarded(self: object, *args: object, **kwargs: object) -> object:
            bound = bind(signature, self, args, kwargs)
            if bound is not None:
                for text, check in checks:
                    if not check(self, *bound):
                        raise AssertionError(text)
            return fn(self, *args, **kwargs)

        return guarded

    program.run()  # the history is what happened: preconditions judge only the proposed calls
    program.instrument(wrap)
    return {"verdicts": [_verdict(spec, program, guards, signatures, call) for call in calls]}


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
            except _FATAL:
                raise
            except BaseException as exc:
                name, message = describe(exc)
                raise Failure({"kind": "program", "where": "preconditions", "index": None, "line": None,
                               "exc_type": name, "message": f"{method.qname}: {message}"}) from None
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
    violations = []
    for text, check in guards.get(qname, []):
        try:
            ok = bool(check(receiver, *values))
        except _FATAL:
            raise
        except BaseException:
            ok = False
        if not ok:
            violations.append(text)
    if violations:
        return {"allowed": False, "violations": violations, "error": None}
    try:
        fn(receiver, *args, **kwargs)
    except _FATAL:
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


class Context:
    def __init__(self, allowed_imports: frozenset[str]) -> None:
        self.builtins = restricted_builtins(allowed_imports)


JOBS: dict[str, typing.Callable[[dict[str, typing.Any], Context], dict[str, object]]] = {
    "trace": job_trace, "evaluate": job_evaluate, "check": job_check,
}


def run_child(limits: dict[str, typing.Any], workdir: str, was_root: bool, server_pid: int,
              ctx: Context) -> typing.NoReturn:
    """Body of a pre-forked child: confine itself, wait for one request, run it, exit without cleanup."""
    budget = [0]
    try:
        budget = confine(limits, workdir, was_root, server_pid)
        warm_up(ctx)
        request = json.loads(_read_all(REQUEST_FD))
        result = JOBS[request["op"]](request["payload"], ctx)
    except Failure as failure:
        result = {"error": failure.info}
    except MemoryError:
        result = {"error": {"kind": "limit", "limit": "memory", "message": "memory limit exceeded"}}
    except OutputLimit:
        result = {"error": {"kind": "limit", "limit": "output", "message": "output limit exceeded"}}
    except RecursionError:
        result = {"error": {"kind": "limit", "limit": "recursion", "message": "maximum recursion depth"}}
    except BaseException as exc:
        name, message = describe(exc)
        result = {"error": {"kind": "internal", "message": f"{name}: {message}"}}
    if budget[0] < 0:
        result = {"error": {"kind": "limit", "limit": "output", "message": "output limit exceeded"}}
    _write_result(result, int(limits["result_bytes"]))
    os._exit(0)


_WARM_UP = {
    "spec": "class A:\n    def __init__(self):\n        self.d = defaultdict(bool)\n"
            "    def f(self, x):\n        self.d[x] = True\n    def g(self, x):\n        pass\n",
    "demonstrations": ["a = A()\na.f('x')\na.g('y')\n"],
    "candidates": {"A.g": ["self.d[x]", "not self.d[x] or x in self.d"]},
    "history": "a = A()\na.f('x')\n",
    "preconditions": {"A.g": ["self.d[x]"]},
    "calls": [{"target": "a", "method": "g", "args": ["x"], "kwargs": {}}],
}


def warm_up(ctx: Context) -> None:
    """Run every job once on trusted input while waiting: a fresh fork pays copy-on-write faults and lazy
    initialisation on first use, and this moves that cost off the request's latency."""
    source = "from collections import defaultdict\n" + typing.cast(str, _WARM_UP["spec"])
    payload = dict(_WARM_UP, spec=source)
    for job in JOBS.values():
        json.dumps(job(payload, ctx))
    json.loads(json.dumps(payload))


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, CHUNK):
        chunks.append(chunk)
    return b"".join(chunks)


def _write_result(result: dict[str, object], cap: int) -> None:
    try:
        data = json.dumps(result).encode("ascii")
    except MemoryError:
        data = b'{"error": {"kind": "limit", "limit": "memory", "message": "memory limit exceeded"}}'
    if len(data) > cap:
        data = json.dumps({"error": {"kind": "limit", "limit": "result",
                                     "message": f"result of {len(data)} bytes"}}).encode("ascii")
    write_all(RESULT_FD, b"%016x" % len(data) + data)


def write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


# ----------------------------------------------------------------------------------------- the server


@dataclasses.dataclass
class Child:
    """A forked, already confined child waiting for its one request (fork cost stays off the latency)."""

    pid: int
    request: int
    result: int
    workdir: str
    status: int | None = None
    cpu_s: float = 0.0


class Server:
    """Reads requests, hands each to a fresh child, enforces the wall clock, forwards the result.

    The answer is sent as soon as the child's result is complete; killing, reaping and removing its
    directory, and forking the next child, happen after that, off the caller's latency.
    """

    def __init__(self, requests: typing.BinaryIO, responses: int, allowed: frozenset[str],
                 limits: dict[str, typing.Any]) -> None:
        self.requests, self.responses, self.limits = requests, responses, limits
        self.was_root = os.geteuid() == 0
        self.ctx = Context(allowed)
        self.pid = os.getpid()

    def serve_forever(self) -> None:
        child = self.prepare()
        try:
            for line in self.requests:
                header, payload = self.handle(child, line)
                self.send(header, payload)
                self.discard(child)
                child = self.prepare()
        finally:
            self.discard(child)

    def send(self, header: dict[str, object], payload: bytes = b"") -> None:
        data = json.dumps(header).encode("ascii") + b"\n"
        if header.get("status") == "ok":
            data += payload + b"\n"
        write_all(self.responses, data)

    def prepare(self) -> Child:
        workdir = tempfile.mkdtemp(prefix="sandbox-")
        if self.was_root:
            os.chown(workdir, NOBODY, NOBODY)
        request_read, request_write = os.pipe()
        result_read, result_write = os.pipe()
        pid = os.fork()
        if pid == 0:
            try:
                # Via high numbers: the pipes may themselves sit on 3 or 4.
                os.dup2(request_read, SPARE_FD)
                os.dup2(result_write, SPARE_FD + 1)
                os.dup2(SPARE_FD, REQUEST_FD)
                os.dup2(SPARE_FD + 1, RESULT_FD)
                run_child(self.limits, workdir, self.was_root, self.pid, self.ctx)
            finally:
                os._exit(70)
        os.close(request_read)
        os.close(result_write)
        with contextlib.suppress(OSError):
            os.setpgid(pid, pid)
        return Child(pid, request_write, result_read, workdir)

    def discard(self, child: Child) -> None:
        """Kill (if still running), reap, close and remove: nothing of the child outlives its request."""
        if child.status is None:
            try:
                os.killpg(child.pid, signal.SIGKILL)
            except OSError:
                os.kill(child.pid, signal.SIGKILL)
            self.reap(child)
        for fd in (child.request, child.result):
            with contextlib.suppress(OSError):
                os.close(fd)
        shutil.rmtree(child.workdir, ignore_errors=True)

    @staticmethod
    def reap(child: Child) -> None:
        _, status, usage = os.wait4(child.pid, 0)
        child.status, child.cpu_s = status, usage.ru_utime + usage.ru_stime

    def handle(self, child: Child, request: bytes) -> tuple[dict[str, object], bytes]:
        try:
            write_all(child.request, request)
            os.close(child.request)
        except OSError:
            pass
        deadline = time.monotonic() + float(self.limits["timeout_s"])
        pidfd = os.pidfd_open(child.pid)
        try:
            how, data = self.collect(child, pidfd, deadline)
        finally:
            os.close(pidfd)
        return self.outcome(child, how, data)

    def collect(self, child: Child, pidfd: int, deadline: float) -> tuple[str, bytes]:
        """Read the length-prefixed result without waiting for the child's exit (teardown costs ms).

        Returns ("done", result), ("gone", partial) when the child exited first, ("timeout", b"") or
        ("result", b"") when it announced or sent more than the result limit.
        """
        cap = int(self.limits["result_bytes"]) + 1024
        buffer = bytearray()
        expected: int | None = None
        eof = False
        while True:
            if expected is None and len(buffer) >= LENGTH_CHARS:
                try:
                    expected = LENGTH_CHARS + int(buffer[:LENGTH_CHARS], 16)
                except ValueError:
                    expected = -1
            if expected is not None and (expected < 0 or expected > cap):
                return "result", b""
            if expected is not None and len(buffer) >= expected:
                return "done", bytes(buffer[LENGTH_CHARS:expected])
            if eof and child.status is not None:
                return "gone", bytes(buffer)
            remaining = deadline - time.monotonic()
            watched = ([] if eof else [child.result]) + ([] if child.status is not None else [pidfd])
            ready = select.select(watched, [], [], remaining)[0] if remaining > 0 else []
            if not ready:
                return "timeout", b""
            if child.result in ready:
                data = os.read(child.result, CHUNK)
                eof = not data
                buffer += data
                if len(buffer) > cap:
                    return "result", b""
            if pidfd in ready:
                self.reap(child)

    def outcome(self, child: Child, how: str, data: bytes) -> tuple[dict[str, object], bytes]:
        if how == "timeout":
            return {"status": "limit", "limit": "timeout",
                    "message": f"no result within {self.limits['timeout_s']} s"}, b""
        if how == "result":
            return {"status": "limit", "limit": "result", "message": "result too large"}, b""
        if how == "done" and data.isascii() and b"\n" not in data:
            return {"status": "ok", "size": len(data)}, data
        if child.status is None:
            return {"status": "crash", "message": "malformed result"}, b""
        status = child.status
        if os.WIFSIGNALED(status):
            sig = os.WTERMSIG(status)
            over_cpu = child.cpu_s >= float(self.limits["cpu_s"])
            if sig == signal.SIGXCPU or (sig == signal.SIGKILL and over_cpu):
                return {"status": "limit", "limit": "cpu", "message": f"used {child.cpu_s:.1f} s of CPU"}, b""
            return {"status": "crash", "message": f"child killed by signal {sig}"}, b""
        code = os.waitstatus_to_exitcode(status)
        return {"status": "crash", "message": f"child exited with code {code} without a result"}, b""


def main() -> None:
    request_fd, response_fd = int(sys.argv[1]), int(sys.argv[2])
    config = json.loads(sys.argv[3])
    allowed = frozenset(config["allowed_imports"])
    for name in sorted(allowed):
        __import__(name)
    problem = isolate_network(ctypes.CDLL(None, use_errno=True), os.geteuid() == 0)
    server = Server(os.fdopen(request_fd, "rb"), response_fd, allowed, config["limits"])
    server.send({"status": "hello", "network_isolated": problem is None, "detail": problem})
    gc.collect()
    gc.freeze()
    server.serve_forever()


if __name__ == "__main__":
    main()

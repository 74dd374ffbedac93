"""Generic JSON events → a program over the user's spec (docs/converting.md).

An event is `{"actor": "user", "act": "INFORM", "args": ["city"]}`: `actor` names an object the setup creates,
`act` a method of its class in the spec, `args` its arguments. Arguments are written as Python literals of
str, int, float, bool or None only (their repr), so nothing in a log can become code.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path
from typing import Any

from precond.convert.shape import ConvertError, expect, key, load_json
from precond.programs.checks import ProgramProblem, instance_classes
from precond.programs.history import event_call
from precond.programs.spec import read_methods

LITERALS = (str, int, float, bool, type(None))


def _parse(source: str, name: str) -> ast.Module:
    try:
        return ast.parse(source)
    except SyntaxError as exc:
        raise ConvertError(f"{name}, line {exc.lineno}: SyntaxError: {exc.msg}") from None


def default_setup(spec: ast.Module, spec_name: str) -> str:
    """One object per spec class, in the spec's order, named after it in lower case; an `__init__` parameter
    must name an object made before it (`system = SYSTEM(user)`). Otherwise give `--setup`."""
    made: list[str] = []
    lines = []
    for node in spec.body:
        if not isinstance(node, ast.ClassDef):
            continue
        init = next((item for item in node.body if isinstance(item, ast.FunctionDef) and item.name == "__init__"),
                    None)
        params = [a.arg for a in (init.args.posonlyargs + init.args.args)[1:]] if init else []
        missing = [p for p in params if p not in made]
        if missing:
            raise ConvertError(f"{spec_name}: class {node.name}: cannot tell what to pass for {', '.join(missing)} "
                               "(no object of that name is made before it); give the setup with --setup")
        variable = node.name.lower()
        lines.append(f"{variable} = {node.name}({', '.join(params)})")
        made.append(variable)
    if not lines:
        raise ConvertError(f"{spec_name}: no class: a spec declares its agent's and its observations' classes")
    return "\n".join(lines) + "\n"


def literal(value: Any, path: Path, where: str) -> str:
    if not isinstance(value, LITERALS) or (isinstance(value, float) and not math.isfinite(value)):
        raise ConvertError(f"{path}: {where}: {type(value).__name__} {json_text(value)} is not a str, int, "
                           "float, bool or null")
    return repr(value)


def json_text(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def trajectories(path: Path) -> list[list[Any]]:
    """A list of events is one trajectory; a list of lists, several."""
    data = expect(load_json(path), list, path, "")
    runs: list[list[Any]] = data if data and all(isinstance(item, list) for item in data) else [data]
    return runs


def program(events: list[Any], setup: str, classes: dict[str, str], methods: dict[str, Any], path: Path,
            where: str) -> str:
    lines = [setup.rstrip("\n")]
    for index, event in enumerate(events):
        at = f"{where}[{index}]"
        expect(event, dict, path, at)
        unknown = set(event) - {"actor", "act", "args"}
        if unknown:
            raise ConvertError(f"{path}: {at}: unknown key {sorted(unknown)[0]!r} (an event has actor, act, args)")
        actor = key(event, "actor", str, path, at)
        act = key(event, "act", str, path, at)
        args = expect(event.get("args", []), list, path, f"{at}.args")
        try:  # the service's own check of an event: the same words, "did you mean" and argument count
            call = event_call(classes, methods, actor, act, len(args), at or "event")
        except ProgramProblem as exc:
            raise ConvertError(f"{path}: {exc.problem.message}") from None
        rendered = ", ".join(literal(arg, path, f"{at}.args[{n}]") for n, arg in enumerate(args))
        lines.append(f"{call}({rendered})")
    return "\n".join(lines) + "\n"


def convert(events_file: Path, spec_file: Path, setup_file: Path | None = None) -> tuple[str, list[str]]:
    """The spec's text and one program per trajectory of the events file."""
    try:
        spec = spec_file.read_text(encoding="utf-8")
        setup = None if setup_file is None else setup_file.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConvertError(f"{exc.filename}: cannot read: {exc.strerror}") from None
    tree = _parse(spec, str(spec_file))
    methods = read_methods(tree)
    if setup is None:
        setup = default_setup(tree, str(spec_file))
    classes = instance_classes([_parse(setup, str(setup_file))], {m.cls for m in methods.values()})
    if not classes:
        raise ConvertError(f"{setup_file or spec_file}: the setup makes no object of a spec class")
    runs = trajectories(events_file)
    return spec, [program(events, setup, classes, methods, events_file, f"[{n}]" if len(runs) > 1 else "")
                  for n, events in enumerate(runs)]

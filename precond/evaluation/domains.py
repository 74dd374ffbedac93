"""The evaluation domains read from `../shared/data`: what inference sees, and where scores are taken.

A `Domain` keeps the two worlds apart: `spec` and `demonstrations` are what may go into an InferRequest;
`gt` (ground-truth assertions) and the test trajectories are for scoring only.

Points, i.e. where C_a is measured (see `evaluation.metrics`), are sandbox `Point(test index, position,
args)`. Positions are the sandbox's: indexes into the main body, which for an SGD dialog is the module body
(`user = USER()` is 0, `system = SYSTEM(user)` is 1, step k is k + 2) and for an ALFWorld trajectory the
body of its single function (`env = Environment()` is 0, `agent = Agent(env)` is 1, then one statement per
step except the out-of-spec actions `examine`/`look`/`inventory`, which the converter wrote no call for).

* SGD (data README): every position after the two setup lines, user and system steps alike, crossed with
  every value of `system_action_args[action]` (one point per position for actions without parameters).
* ALFWorld (valid_unseen, as the paper): the states before each in-spec action. Argument domains come from
  the simulator's admissible commands (`test_admissible_commands.json`), never from the ground truth:
  - two-argument actions (take, put, clean, heat, cool): the tuples offered in that very state;
  - one-argument actions (goto, open, close, toggle): every value offered for that action anywhere in the
    trajectory, at every state, as SGD's per-domain value lists are used at every position. Per-state
    offers would only contain what the simulator accepts there (e.g. `open` only for the closed
    receptacle the agent stands at), so "always allowed" would score P = 1 and the metric would say
    nothing. `ARG_MODES` also offers "trajectory" (union over the trajectory for two-argument actions as
    well) as a stricter variant.
"""

from __future__ import annotations

import ast
import json
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

from precond.programs import Method, main_body, read_methods
from precond.sandbox.types import Point

ArgMode = Literal["state", "trajectory"]
ARG_MODES: tuple[ArgMode, ...] = ("state", "trajectory")
SGD_SETUP_STATEMENTS = 2
ALFWORLD_SETUP_STATEMENTS = 2
ALFWORLD_TEST_SPLIT = "valid_unseen"
TWO_ARGUMENT = ("take", "put", "clean", "heat", "cool")
_T = TypeVar("_T")
READ_FAILURES = (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError, SyntaxError, RecursionError)
"""What reading a domain's files can raise when they are not what the data READMEs describe."""


class DomainDataError(ValueError):
    """A domain directory or file that cannot be read as the data READMEs describe. The message names the path:
    an evaluation stops there rather than scoring the domains it could read as if they were all of them."""

_COMMANDS: tuple[tuple[str, re.Pattern[str]], ...] = (
    ("goto", re.compile(r"^go to (?P<a>.+)$")),
    ("open", re.compile(r"^open (?P<a>.+)$")),
    ("close", re.compile(r"^close (?P<a>.+)$")),
    ("take", re.compile(r"^take (?P<a>.+?) from (?P<b>.+)$")),
    ("put", re.compile(r"^put (?P<a>.+?) (?:in/on|in|on) (?P<b>.+)$")),
    ("clean", re.compile(r"^clean (?P<a>.+?) with (?P<b>.+)$")),
    ("heat", re.compile(r"^heat (?P<a>.+?) with (?P<b>.+)$")),
    ("cool", re.compile(r"^cool (?P<a>.+?) with (?P<b>.+)$")),
    ("toggle", re.compile(r"^use (?P<a>.+)$")),
)


@dataclass(frozen=True)
class Domain:
    name: str
    benchmark: str  # "sgd" | "star" | "alfworld"
    spec: str
    demonstrations: tuple[str, ...]
    actions: tuple[str, ...]  # qualified names, as the engine reports them ("SYSTEM.INFORM")
    test: tuple[str, ...]  # test programs, the "demonstrations" of the scoring sandbox calls
    test_ids: tuple[str, ...]
    points: dict[str, list[Point]]
    gt: dict[str, list[str]] = field(repr=False)  # scoring only: never in a prompt or request
    inference_key: str = ""  # domains that differ only in scoring points share their inference

    @property
    def infer_as(self) -> str:
        return self.inference_key or self.name

    @property
    def n_points(self) -> int:
        return sum(len(p) for p in self.points.values())


def parse_command(command: str) -> tuple[str, tuple[str, ...]] | None:
    """An admissible command as (action, args); None for commands outside the spec (look, examine, ...)."""
    for action, pattern in _COMMANDS:
        match = pattern.match(command.strip())
        if match:
            return action, tuple(v for v in match.groupdict().values() if v is not None)
    return None


# ---- SGD -------------------------------------------------------------------------------------------------


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


def sgd_domain_files(data_dir: Path) -> list[Path]:
    return sorted(p for p in data_dir.glob("*.json") if p.is_file())


def _methods(spec: str, cls: str) -> list[Method]:
    """The methods of one spec class (static reading; the spec is data, never imported)."""
    methods = [m for m in read_methods(ast.parse(spec)).values() if m.cls == cls]
    if not methods:
        raise ValueError(f"spec has no class {cls} with methods")
    return methods


def _method_params(spec: str, cls: str) -> dict[str, tuple[str, ...]]:
    """Positional parameter names per method of one spec class."""
    return {m.name: m.positional for m in _methods(spec, cls)}


def _sgd_points(data: dict[str, Any], params: dict[str, tuple[str, ...]]) -> dict[str, list[Point]]:
    points: dict[str, list[Point]] = {}
    for action in data["system_actions"]:
        values: Sequence[tuple[object, ...]]
        values = [(v,) for v in data["system_action_args"].get(action, [])] if params[action] else [()]
        points[f"SYSTEM.{action}"] = [
            Point(i, SGD_SETUP_STATEMENTS + k, args)
            for i, dialog in enumerate(data["test"])
            for k in range(len(dialog["steps"]))
            for args in values
        ]
    return points


def dialog_benchmark(data: dict[str, Any]) -> str:
    """`star` for the STAR tasks, `sgd` for every other file of the SGD format."""
    return "star" if str(data.get("dataset", "")).startswith("STAR") else "sgd"


def _check_sgd_dialog(dialog: dict[str, Any]) -> None:
    """Positions are computed from `steps`; make sure the program has exactly one statement per step."""
    body = main_body(ast.parse(dialog["program"]))
    if len(body) != SGD_SETUP_STATEMENTS + len(dialog["steps"]):
        steps = len(dialog["steps"])
        raise ValueError(f"dialog {dialog['dialogue_id']}: {len(body)} statements for {steps} steps")


def load_sgd(path: Path) -> Domain:
    """One SGD service, or one STAR task (the same file format; its `dataset` names STAR, its benchmark is
    `star`, so the tables keep human-agent logs apart from SGD's simulated ones)."""
    data = _read_json(path)
    for dialog in data["test"]:
        _check_sgd_dialog(dialog)
    params = _method_params(data["spec_program"], "SYSTEM")
    return Domain(
        name=data["service"],
        benchmark=dialog_benchmark(data),
        spec=data["spec_program"],
        demonstrations=tuple(d["program"] for d in data["demos"]),
        actions=tuple(f"SYSTEM.{a}" for a in data["system_actions"]),
        test=tuple(d["program"] for d in data["test"]),
        test_ids=tuple(d["dialogue_id"] for d in data["test"]),
        points=_sgd_points(data, params),
        gt={f"SYSTEM.{a}": list(v) for a, v in data["gt_preconditions"].items()},
    )


# ---- ALFWorld --------------------------------------------------------------------------------------------


def gt_assertions(spec_gt: str, cls: str) -> dict[str, list[str]]:
    """`assert` expressions of each method of `cls`, in order (read statically from alfworld_spec_gt.py)."""
    out: dict[str, list[str]] = {}
    for method in _methods(spec_gt, cls):
        tests = [ast.unparse(s.test) for s in method.node.body if isinstance(s, ast.Assert)]
        if tests:
            out[method.qualname] = tests
    return out


def action_positions(trajectory: dict[str, Any]) -> list[tuple[int, dict[str, Any]]]:
    """(body position, step) of every action step in order; out-of-spec actions get position -1."""
    out: list[tuple[int, dict[str, Any]]] = []
    position = ALFWORLD_SETUP_STATEMENTS
    for step in trajectory["steps"]:
        written = step["kind"] != "action" or step.get("in_spec", True)
        if step["kind"] == "action":
            out.append((position if written else -1, step))
        position += 1 if written else 0
    return out


def _offers(commands: Iterable[str]) -> dict[str, set[tuple[str, ...]]]:
    found: dict[str, set[tuple[str, ...]]] = {}
    for command in commands:
        parsed = parse_command(command)
        if parsed is not None:
            found.setdefault(parsed[0], set()).add(parsed[1])
    return found


def alfworld_points(
    trajectory: dict[str, Any], admissible: Sequence[Sequence[str]], index: int, actions: Sequence[str],
    mode: ArgMode = "state",
) -> dict[str, list[Point]]:
    """Points of one test trajectory; `admissible[k]` are the commands offered before action t = k + 1."""
    states = [(pos, step) for pos, step in action_positions(trajectory) if pos >= 0]
    per_state = [_offers(admissible[step["t"] - 1]) for _, step in states]
    for offers, (_, step) in zip(per_state, states, strict=True):  # the executed action was offered too
        offers.setdefault(step["fn"], set()).add(tuple(step["args"]))
    union: dict[str, set[tuple[str, ...]]] = {}
    for offers in [*per_state, _offers(c for commands in admissible for c in commands)]:
        for action, args in offers.items():
            union.setdefault(action, set()).update(args)
    points: dict[str, list[Point]] = {}
    for action in actions:
        for (position, _), offers in zip(states, per_state, strict=True):
            local = mode == "state" and action in TWO_ARGUMENT
            values = offers.get(action, set()) if local else union.get(action, set())
            points.setdefault(f"Agent.{action}", []).extend(Point(index, position, a) for a in sorted(values))
    return points


def _agent_actions(spec: str) -> list[str]:
    """The Agent methods with stub bodies: the actions whose preconditions are inferred."""
    return [m.name for m in _methods(spec, "Agent") if m.stub]


def load_alfworld(data_dir: Path, mode: ArgMode = "state", limit: int | None = None) -> Domain:
    demos = _read_json(data_dir / "demos.json")
    spec = (data_dir / "alfworld_spec.py").read_text(encoding="utf-8")
    trajectories = [t for t in _read_json(data_dir / "test.json")["trajectories"]
                    if t["split"] == ALFWORLD_TEST_SPLIT and not t.get("same_scene_as_demo")][:limit]
    admissible = _read_json(data_dir / "test_admissible_commands.json")["admissible_commands"]
    actions = _agent_actions(spec)
    points: dict[str, list[Point]] = {f"Agent.{a}": [] for a in actions}
    for index, trajectory in enumerate(trajectories):
        found = alfworld_points(trajectory, admissible[trajectory["id"]], index, actions, mode)
        for action, more in found.items():
            points[action].extend(more)
    gt_text = (data_dir / "alfworld_spec_gt.py").read_text(encoding="utf-8")
    return Domain(
        name="alfworld" if mode == "state" else f"alfworld-{mode}",
        benchmark="alfworld",
        spec=spec,
        demonstrations=tuple(t["program"] for t in demos["trajectories"]),
        actions=tuple(f"Agent.{a}" for a in actions),
        test=tuple(t["program"] for t in trajectories),
        test_ids=tuple(t["id"] for t in trajectories),
        points=points,
        gt=gt_assertions(gt_text, "Agent"),
        inference_key="alfworld",
    )


def load_domains(data_dir: Path, alfworld_mode: ArgMode = "state") -> list[Domain]:
    """A data directory is either one of the SGD format (one JSON per service or STAR task) or the ALFWorld
    one; all of it or `DomainDataError` naming the directory or file that is missing or malformed."""
    if not data_dir.is_dir():
        problem = "not a directory" if data_dir.exists() else "does not exist"
        raise DomainDataError(f"domain directory {data_dir}: {problem}")
    if (data_dir / "demos.json").exists():
        return [read_domain(data_dir, lambda path: load_alfworld(path, alfworld_mode))]
    files = sgd_domain_files(data_dir)
    if not files:
        raise DomainDataError(f"domain directory {data_dir}: neither SGD domain files (*.json) nor ALFWorld's "
                              "demos.json")
    return [read_domain(p, load_sgd) for p in files]


def read_domain(path: Path, loader: Callable[[Path], _T]) -> _T:
    """`loader(path)`, or `DomainDataError` naming `path` and what was wrong with it."""
    try:
        return loader(path)
    except DomainDataError:
        raise
    except READ_FAILURES as exc:
        raise DomainDataError(f"malformed domain data {path}: {_failure(exc)}") from exc


def _failure(exc: BaseException) -> str:
    if isinstance(exc, KeyError):
        return f"missing field {exc}"
    if isinstance(exc, OSError) and exc.filename:
        return f"cannot read {exc.filename}: {exc.strerror or type(exc).__name__}"
    return f"{type(exc).__name__}: {exc}"

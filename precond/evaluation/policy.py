"""`precond eval policy`: next-action prediction on SGD test dialogs (the paper's section 4.3).

At every system turn the history is the dialog so far and the policy predicts the turn's actions with one
`NextActionRequest` (max_actions > 1). A turn with a service call is split where the environment answers
(`system.set_query_status(...)`): that status is an observation, not an action, so it is appended to the
history as the data has it and the rest of the turn is predicted after it. The predictions of a turn's
segments together are compared with the turn's reference actions (system acts and service calls) as
multisets of calls: turn F1 (`evaluation.metrics.turn_f1`), averaged over turns.

Precondition compatibility is the share of predicted actions that the GROUND-TRUTH preconditions allow in
the state where they were predicted, checked with `Engine.check` (the sandbox). A prediction that is not a
call of an action function (the engine returns the model's line as is when even its first line is no
action, typically a `user.` act) counts as incompatible in `compatibility`; `compatibility_of_actions`
leaves such lines out, i.e. it judges only what the policy proposed as a system action.

When the engine refuses a request because the history itself violates the preconditions it was given
(inferred preconditions that contradict the dialog), the refusal is counted (`engine_errors`) and that
segment is predicted without preconditions, as a client would have to.

Policy configurations, `<preconditions>/<use>/shots=N[/bc|/react]` (`bc`: behaviour cloning, the code model
fine-tuned on the domain's demonstrations, precond/evaluation/bc.py; `react`: the base model writing a thought before
each action, prompted on ALFWorld with ReAct's hand-written thoughts in its demonstration and on SGD, whose
demonstrations carry none, zero-shot; without either the base model, prompted: Act):
  preconditions: none | inferred | gt  (inferred: read from the precondition cache, see `--inferred-from`)
  use:           plain (no precondition use: the model's greedy lines, unverified) | prompt (written into the
                 prompt's spec) | verify (Algorithm 1's verified sampling, mode 'sample') | both |
                 constrained (mode 'constrained': the model chooses among the calls the preconditions allow,
                 action first, then its arguments) | constrained-lines (the same, the likeliest whole line:
                 `options.choose_by: line`)
"""

from __future__ import annotations

import ast
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from tqdm import tqdm

from precond.evaluation.cache import JsonCache
from precond.evaluation.domains import SGD_SETUP_STATEMENTS, Domain
from precond.evaluation.metrics import mean, percentile, turn_f1
from precond_client.schemas import (
    CheckRequest,
    CheckResponse,
    NextActionOptions,
    NextActionRequest,
    NextActionResponse,
)
from precond_client.schemas.errors import PrecondError

USES = {"plain": (False, False), "prompt": (True, False), "verify": (False, True), "both": (True, True),
        "constrained": (False, True), "constrained-lines": (False, True)}
SOURCES = ("none", "inferred", "gt")
POLICIES = ("bc", "react")
GRIDS: dict[str, tuple[str, ...]] = {
    "default": ("none/plain/shots=1", "inferred/prompt/shots=1", "inferred/verify/shots=1",
                "inferred/both/shots=1", "gt/verify/shots=1", "gt/both/shots=1",
                "none/plain/shots=3", "inferred/both/shots=3", "gt/both/shots=3"),
    "small": ("none/plain/shots=1", "inferred/verify/shots=1", "gt/verify/shots=1"),
    "modes": ("none/plain/shots=1", "inferred/verify/shots=1", "inferred/constrained/shots=1",
              "inferred/constrained-lines/shots=1"),
    "bc": ("none/plain/shots=1", "inferred/verify/shots=1", "inferred/constrained/shots=1",
           "none/plain/shots=0/bc", "inferred/verify/shots=0/bc", "inferred/constrained/shots=0/bc"),
    "paper": ("none/plain/shots=1", "inferred/verify/shots=1", "inferred/constrained/shots=1",
              "none/plain/shots=1/react", "inferred/verify/shots=1/react", "inferred/constrained/shots=1/react",
              "none/plain/shots=0/bc", "inferred/verify/shots=0/bc", "inferred/constrained/shots=0/bc"),
}
"""`paper`: the paper's policy table on ALFWorld (Act, ReAct, BC; each alone, with Algorithm 1, constrained)."""
MAX_ACTIONS = 5


class PolicyEngine(Protocol):
    """The two engine operations the policy evaluation uses (`engine.engine.Engine` satisfies it)."""

    def next_action(self, request: NextActionRequest) -> NextActionResponse: ...

    def check(self, request: CheckRequest) -> CheckResponse: ...


@dataclass(frozen=True)
class PolicyConfig:
    name: str
    source: str
    in_prompt: bool
    verify: bool
    shots: int
    mode: str = "sample"
    choose_by: str = "action"
    policy: str = "act"
    """'act': the base model prompted with the demonstrations; 'bc': the model fine-tuned on them (evaluation.bc);
    'react': the base model prompted with demonstrations that carry thoughts, writing one before each action
    (`options.think`; ALFWorld's demonstrations carry ReAct's thoughts, precond/evaluation/react_thoughts.py, SGD's
    none, so there the model's thoughts are zero-shot)."""


def parse_policy_config(name: str) -> PolicyConfig:
    parts = name.split("/")
    policy = parts.pop() if len(parts) == 4 and parts[3] in POLICIES else "act"
    shots = parts[-1].startswith("shots=")
    if len(parts) != 3 or parts[0] not in SOURCES or parts[1] not in USES or not shots:
        raise ValueError(f"policy config {name!r}: expected <source>/<use>/shots=N[/bc|/react], see "
                         "precond/evaluation/policy.py")
    if parts[0] == "none" and parts[1] != "plain":
        raise ValueError(f"policy config {name!r}: without preconditions only 'plain' makes sense")
    in_prompt, verify = USES[parts[1]]
    mode = "constrained" if parts[1].startswith("constrained") else "sample"
    choose_by = "line" if parts[1] == "constrained-lines" else "action"
    return PolicyConfig(name, parts[0], in_prompt, verify, int(parts[2].removeprefix("shots=")), mode, choose_by,
                        policy)


def expand_policy(names: str) -> list[PolicyConfig]:
    out: list[str] = []
    for item in (n.strip() for n in names.split(",") if n.strip()):
        out.extend(GRIDS.get(item, (item,)))
    return [parse_policy_config(n) for n in dict.fromkeys(out)]


def normalize_call(text: str) -> str:
    """One spelling per call (quotes, spaces), as the engine reports predicted calls (`ast.unparse`)."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError:
        return text.strip()
    return ast.unparse(tree)


@dataclass(frozen=True)
class Segment:
    """Part of a system turn predicted in one request: the history before it and the reference actions."""

    key: str
    turn: int
    history: str
    reference: tuple[str, ...]


def segments(dialog: dict[str, Any]) -> Iterator[Segment]:
    """System turns, split after each `set_query_status` (an observation inside the turn)."""
    lines = dialog["program"].splitlines()
    steps = dialog["steps"]
    for turn_index, turn in enumerate(dialog["turns"]):
        if turn["speaker"] != "SYSTEM":
            continue
        start, end = turn["steps"]
        cut = start
        for k in range(start, end + 1):
            if k == end or steps[k]["kind"] == "query_status":
                if k > cut:  # nothing after a status that ends the turn: no request to make
                    yield _segment(lines, steps, turn_index, cut, k)
                cut = k + 1


def _segment(lines: Sequence[str], steps: Sequence[dict[str, Any]], turn: int, start: int, end: int
             ) -> Segment:
    history = "\n".join(lines[: SGD_SETUP_STATEMENTS + start]) + "\n"
    reference = tuple(normalize_call(lines[SGD_SETUP_STATEMENTS + k]) for k in range(start, end)
                      if steps[k]["kind"] in ("system_act", "service_call"))
    return Segment(f"{turn}:{start}", turn, history, reference)


def _no_replay() -> float:
    return 0.0


def _predict(engine: PolicyEngine, domain: Domain, config: PolicyConfig, preconditions: dict[str, list[str]],
             segment: Segment, seed: int, replayed: Callable[[], float] = _no_replay) -> dict[str, Any]:
    """One request; `replayed` gives the seconds of remembered completions it used (evaluation.memo)."""
    used = preconditions if config.source != "none" else {}
    request = NextActionRequest(
        spec=domain.spec, preconditions=used, demonstrations=list(domain.demonstrations[: config.shots]),
        history=segment.history,
        options=NextActionOptions(max_actions=MAX_ACTIONS, preconditions_in_prompt=config.in_prompt,
                                  verify=config.verify, seed=seed, mode=config.mode,  # type: ignore[arg-type]
                                  choose_by=config.choose_by,  # type: ignore[arg-type]
                                  think=config.policy == "react",
                                  fallback="greedy" if config.mode == "sample" else "none"),
    )
    start = time.perf_counter()
    error = None
    try:
        response = engine.next_action(request)
    except PrecondError as exc:
        # The engine runs the history under the preconditions; when inferred ones contradict what the dialog
        # already did it refuses (422). Record that, and fall back to the policy without preconditions.
        error = f"{exc.kind}: {exc.message}"
        plain = request.options.model_copy(update={"preconditions_in_prompt": False, "verify": False,
                                                   "mode": "sample"})
        response = engine.next_action(request.model_copy(update={"preconditions": {}, "options": plain}))
    seconds = time.perf_counter() - start + replayed()
    # the paper's Algorithm 1 falls back to the greedy line; a line that is no action call counts as written;
    # "nothing allowed" (mode 'constrained') is no prediction at all
    predicted = [normalize_call(a.call if a.call is not None else a.rejected[0].call if a.rejected else "")
                 for a in response.actions if not a.nothing_allowed]
    return {"predicted": predicted, "reference": list(segment.reference), "seconds": seconds, "error": error,
            "nothing_allowed": sum(a.nothing_allowed for a in response.actions)}



def receivers(history: str) -> dict[str, str]:
    """`system = SYSTEM(user)` -> {"system": "SYSTEM"}: which class a predicted call's receiver is."""
    found: dict[str, str] = {}
    for node in ast.parse(history).body:
        call = node.value if isinstance(node, ast.Assign) else None
        if isinstance(node, ast.Assign) and isinstance(call, ast.Call) and isinstance(call.func, ast.Name):
            found.update({t.id: call.func.id for t in node.targets if isinstance(t, ast.Name)})
    return found


def action_of(call: str, known: dict[str, str]) -> str | None:
    """The qualified action a predicted line calls (`SYSTEM.INFORM`), or None when it is no single call."""
    try:
        node = ast.parse(call, mode="eval").body
    except SyntaxError:
        return None
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and isinstance(node.func.value, ast.Name)):
        return None
    return f"{known.get(node.func.value.id, '?')}.{node.func.attr}"


def _compatible(engine: PolicyEngine, domain: Domain, history: str, calls: list[str]) -> list[bool]:
    """Each predicted call judged by the GT in the segment's state (system acts do not change the state).

    Only calls of the domain's actions are judged; anything else the policy emitted (a user act, text) is
    incompatible without asking the sandbox.
    """
    known = receivers(history)
    judged = [c for c in calls if action_of(c, known) in domain.actions]
    if not judged:
        return [False] * len(calls)
    try:
        verdicts = engine.check(CheckRequest(spec=domain.spec, preconditions=domain.gt, history=history,
                                             calls=[*judged])).results
    except PrecondError:
        return [False] * len(calls)
    allowed = iter(v.allowed for v in verdicts)
    return [next(allowed) if action_of(c, known) in domain.actions else False for c in calls]


def run_policy(engine: PolicyEngine, domain: Domain, config: PolicyConfig,
               preconditions: dict[str, list[str]], dialogs: Sequence[dict[str, Any]], cache: JsonCache,
               max_turns: int | None, seed: int = 0, replayed: Callable[[], float] = _no_replay,
               progress: Callable[[], None] | None = None) -> list[dict[str, Any]]:
    """Every selected segment's prediction, from the cache when present; one cache file per dialog.

    Compatibility is judged afresh on every run (a sandbox check is milliseconds), so a cached prediction is
    never scored under an outdated rule or ground truth.
    """
    results: list[dict[str, Any]] = []
    for dialog in tqdm(dialogs, desc=f"{domain.name} {config.name}", unit="dialog", leave=False,
                       disable=progress is not None):
        done: dict[str, Any] = cache.get("policy", domain.name, config.name, dialog["dialogue_id"]) or {}
        turns = sorted({s.turn for s in segments(dialog)})[:max_turns]
        for segment in (s for s in segments(dialog) if s.turn in turns):
            if segment.key not in done:
                done[segment.key] = _predict(engine, domain, config, preconditions, segment, seed, replayed) | {
                    "turn": segment.turn}
                cache.put(done, "policy", domain.name, config.name, dialog["dialogue_id"])
            if progress is not None:
                progress()
            predicted = done[segment.key]["predicted"]
            known = receivers(segment.history)
            results.append(done[segment.key] | {
                "dialog": dialog["dialogue_id"],
                "compatible": _compatible(engine, domain, segment.history, predicted),
                "is_action": [action_of(c, known) in domain.actions for c in predicted]})
    return results


def summarize_policy(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Turn F1 over turns (segments merged), compatibility over predicted actions, latency over requests."""
    turns: dict[tuple[str, int], tuple[list[str], list[str]]] = {}
    for r in results:
        predicted, reference = turns.setdefault((r["dialog"], r["turn"]), ([], []))
        predicted.extend(r["predicted"])
        reference.extend(r["reference"])
    scores = [turn_f1(p, ref) for p, ref in turns.values()]
    compatible = [c for r in results for c in r["compatible"]]
    of_actions = [c for r in results for c, a in zip(r["compatible"], r.get("is_action", r["compatible"]),
                                                       strict=True) if a]
    latency = [r["seconds"] for r in results]
    errors = sum(1 for r in results if r.get("error"))
    return {"turns": len(turns), "requests": len(results), "actions": len(compatible), "engine_errors": errors,
            "f1": mean(s.f1 for s in scores), "precision": mean(s.precision for s in scores),
            "recall": mean(s.recall for s in scores),
            "compatibility": mean(1.0 if c else 0.0 for c in compatible),
            "compatibility_of_actions": mean(1.0 if c else 0.0 for c in of_actions),
            "non_actions": len(compatible) - len(of_actions),
            "latency_p50_s": percentile(latency, 50), "latency_p95_s": percentile(latency, 95)}

"""The engine's judging of given rules: a check of an agent's calls (`/check-actions`), a precondition set's
validation against its demonstrations, and the verification of a proposed next action. A part of `Engine`
(`engine.py`), apart because none of it infers anything."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

from precond.convert.openai import call_lines, call_schema_problems
from precond.engine import scope
from precond.engine.sandboxed import broken_text, rendered_history, sandbox_call, spec_of
from precond.engine.spec import (
    Spec,
    as_error,
    call_actions,
    check_calls,
    check_preconditions,
    parse_source,
    parse_spec,
    remembered_spec,
)
from precond.programs import checks
from precond_client.schemas import (
    MAX_CALL_CHARS,
    Blocked,
    CallVerdict,
    CheckRequest,
    CheckResponse,
    ValidateResponse,
    rule_status,
)

if TYPE_CHECKING:
    from precond.sandbox import Sandbox



class Checking:
    """The engine's operations that judge rules it is given, on its sandbox."""

    _sandbox: Sandbox

    def _history_violation(self, spec: Spec, preconditions: dict[str, list[str]], history: str) -> str | None:
        """Where the history breaks the preconditions, if it does: its line and the rules that did not hold."""
        if not any(preconditions.values()):
            return None
        judged = sandbox_call(self._sandbox.judge, spec.source, preconditions, history, [],
                              scope.current() or None, warm=scope.warm())
        return broken_text(history, judged.history)

    def _verify(
        self, spec: Spec, preconditions: dict[str, list[str]], history: str, calls: list[str]
    ) -> list[CallVerdict]:
        verdicts = sandbox_call(self._sandbox.check, spec.source, preconditions, history, calls,
                                scope.current() or None, warm=scope.warm())
        return [CallVerdict(call=v.call, allowed=v.allowed, violations=list(v.violations), error=v.error)
                for v in verdicts]

    def check(self, request: CheckRequest, screened: bool = False) -> CheckResponse:
        """`screened`: the gateway rendered the history and the calls and ran the static screen
        (`checks.check_check`) before it queued the job, so the worker does not run it again."""
        spec = remembered_spec(scope.current(), spec_of(request))
        if not screened:
            check_preconditions(spec, request.preconditions, scope.current())
        history = rendered_history(spec.source, request.history)  # parsed by check_calls, once per scope and text
        sent = [c if isinstance(c, str) else c.model_dump() for c in request.calls]
        try:
            calls = call_lines(spec.source, sent, scope=scope.current())
        except checks.ProgramProblem as exc:
            raise as_error(exc) from exc
        if not screened:
            check_calls(spec, request.preconditions, history, calls, scope.current())
        judged = sandbox_call(self._sandbox.judge, spec.source, request.preconditions, history, calls,
                              scope.current() or None, warm=scope.warm())
        broken = call_schema_problems(spec.source, sent, scope.current())  # refused before any rule is asked
        verdicts = [CallVerdict(call=v.call, allowed=False, error=problem) if problem else
                    CallVerdict(call=v.call, allowed=v.allowed, violations=list(v.violations), error=v.error)
                    for v, problem in zip(judged.verdicts, broken, strict=True)]
        actions = call_actions(spec, history, calls, scope.current())
        return CheckResponse(results=[with_status(labelled_verdict(v, spec, request.decided), action, request)
                                      for v, action in zip(verdicts, actions, strict=True)],
                             history_violation=broken_text(history, judged.history))

    def validate(self, spec_text: str, preconditions: dict[str, list[str]],
                 demonstrations: Sequence[str]) -> ValidateResponse:
        """Every demonstrated call each rule would have refused (demonstration, line), from where it holds."""
        spec = parse_spec(spec_text)
        check_preconditions(spec, preconditions)
        demos = list(demonstrations)
        for i, demo in enumerate(demos):
            parse_source(demo, f"demonstrations[{i}]")
        rules = {action: list(dict.fromkeys(r)) for action, r in preconditions.items() if r}
        trace = sandbox_call(self._sandbox.trace, spec.source, demos, scope=scope.current())
        evaluated = sandbox_call(self._sandbox.evaluate, spec.source, demos, rules, scope=scope.current())
        blocked: list[Blocked] = []
        unjudged: dict[str, str] = {}
        raised: dict[str, str] = {}
        occurrences: dict[str, int] = {}
        for action, expressions in rules.items():
            points = evaluated.points.get(action, ())
            results = {r.expression: r for r in evaluated.results.get(action, ())}
            for rule in expressions:
                result = results.get(rule)
                if result is None or result.status == "rejected":
                    unjudged[f"{action}: {rule}"] = (result.reason if result else None) or "not judged"
                    continue
                if result.status == "invalid" and _raised(result.reason):
                    raised[f"{action}: {rule}"] = str(result.reason)
                occurrences[f"{action}: {rule}"] = len(trace.actions[action].occurrences)
                for occ in trace.actions[action].occurrences:
                    try:
                        holds = (result.satisfied >> points.index(occ)) & 1
                    except ValueError:
                        holds = 0
                    if not holds:
                        step = trace.positions[occ.demo][occ.position]
                        blocked.append(Blocked(action=action, rule=rule, demonstration=occ.demo, line=step.line,
                                               call=step.source.strip()[:MAX_CALL_CHARS]))
        return ValidateResponse(blocked=blocked, unjudged=unjudged, raised=raised, occurrences=occurrences)


def _raised(first_violation: str | None) -> bool:
    """The sandbox's first violation of a rule names an exception (`..., args []: AttributeError: ...`), not a
    false answer (`: assertion fails`) or a state it could not copy."""
    return bool(first_violation) and not str(first_violation).endswith(
        (": assertion fails", ": the state could not be copied"))


def labelled_verdict(verdict: CallVerdict, spec: Spec, decided: Mapping[str, Mapping[str, str]]) -> CallVerdict:
    """The verdict with how each rule that refused the call was decided (its action's label for it)."""
    if not verdict.violations or not decided:
        return verdict
    actions = [a for a in decided if a in spec.methods and f".{spec.methods[a].name}(" in verdict.call]
    labels = {rule: label for a in actions for rule, label in decided[a].items()}
    return verdict.model_copy(update={"decided": {v: labels[v] for v in verdict.violations if v in labels}})


def with_status(verdict: CallVerdict, action: str | None, request: CheckRequest) -> CallVerdict:
    """The verdict with the action it judged and what its rule rests on (`rule_status`): allowed because the
    evidence says so, or because nothing is known."""
    if action is None:
        return verdict
    status = rule_status(request.preconditions.get(action, []), request.decided.get(action, {}))
    return verdict.model_copy(update={"action": action, "rule_status": status})


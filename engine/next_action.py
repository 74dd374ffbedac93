"""The paper's Algorithm 1, "Sample Next Action with Verification", for one or several actions in a turn.

Greedy first; if its program fails the preconditions, random samples until one runs, up to `max_attempts`;
otherwise "no verified action" (`call: null`, with every rejected attempt and why), or, only when the caller
asked for it (`options.fallback: "greedy"`), the greedy call with `verified: false`. A line that is not a
call of one of the agent's actions (a user act, free text) is never returned as an action.

The random samples are drawn as one batch and verified
in one sandbox call, then read in order: the same outcome as drawing them one at a time, at a fraction of
the cost.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from engine import prompting
from engine.spec import Spec
from programs.checks import instance_classes
from schemas.api import CallVerdict, NextActionRequest, PredictedAction, Rejection
from schemas.errors import Cancelled

if TYPE_CHECKING:
    from engine.models import CodeModel

NO_ACTION = "no action: the model's line is not a call of an action function"
VerifyFn = Callable[[Spec, dict[str, list[str]], str, list[str]], list[CallVerdict]]


@dataclass(frozen=True)
class Prediction:
    text: str
    call: str | None
    reason: str | None = None


def classify(line: str, receivers: dict[str, str], actions: set[str]) -> Prediction:
    """A prediction counts only if it is one call of an action function; anything else says why not."""
    text = line.strip()
    if not text:
        return Prediction(text, None, "empty line")
    try:
        tree = ast.parse(text)
    except (SyntaxError, ValueError, RecursionError):
        return Prediction(text, None, "not valid Python")
    node = tree.body[0] if len(tree.body) == 1 else None
    call = node.value if isinstance(node, ast.Expr) else None
    if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
            and isinstance(call.func.value, ast.Name)):
        return Prediction(text, None, "not a single method call")
    cls = receivers.get(call.func.value.id)
    name = f"{cls}.{call.func.attr}"
    if name not in actions:
        return Prediction(text, None, f"{name} is not an action function")
    return Prediction(text, ast.unparse(call))


def append_line(history: str, call: str) -> str:
    """Continue the history at the indentation of its last statement (top level or inside the episode)."""
    lines = [line for line in history.splitlines() if line.strip()]
    indent = lines[-1][: len(lines[-1]) - len(lines[-1].lstrip())] if lines else ""
    return f"{history.rstrip()}\n{indent}{call}\n"


class NextActionPlanner:
    def __init__(
        self,
        spec: Spec,
        request: NextActionRequest,
        model: CodeModel,
        verify: VerifyFn,
        cancelled: Callable[[], bool],
    ) -> None:
        self.spec = spec
        self.request = request
        self.options = request.options
        self.model = model
        self.verify = verify
        self.cancelled = cancelled
        self.actions = set(spec.stub_actions) | set(request.preconditions)
        if not isinstance(request.history, str):
            raise TypeError("render a structured history first (engine.engine.history_program)")
        self.history = request.history
        trees = [ast.parse(s) for s in (*request.demonstrations, self.history)]
        self.receivers = instance_classes(trees, {m.cls for m in spec.methods.values()})

    def run(self, progress: Callable[[str, int, int], None]) -> list[PredictedAction]:
        history = self.history
        out: list[PredictedAction] = []
        for step in range(self.options.max_actions):
            if self.cancelled():
                raise Cancelled("job cancelled")
            progress("predict", step, self.options.max_actions)
            predicted = self._one(history, step)
            if predicted is None:
                break
            out.append(predicted)
            if predicted.call is None:
                break  # no action to continue the turn from
            history = append_line(history, predicted.call)
        progress("done", len(out), len(out))
        return out

    def _sample(self, prompt: str, n: int, temperature: float, seed: int) -> list[Prediction]:
        from engine.models import Sampling

        sampling = Sampling(temperature, 0.95, self.options.max_new_tokens, seed)
        texts = self.model.complete(prompt, [""], n, sampling, "line", self.cancelled)[0]
        return [classify(t, self.receivers, self.actions) for t in texts]

    def _check(self, history: str, calls: list[str]) -> list[CallVerdict]:
        return self.verify(self.spec, self.request.preconditions, history, calls) if calls else []

    def _one(self, history: str, step: int) -> PredictedAction | None:
        prompt = prompting.next_action_prompt(
            self.spec, self.request.preconditions, self.request.demonstrations, history,
            self.options.preconditions_in_prompt,
        )
        greedy = self._sample(prompt, 1, 0.0, self.options.seed)[0]
        if greedy.call is None and step > 0:
            return None  # the model hands the turn back: no further action this turn
        tried = [greedy]
        if not self.options.verify:
            if greedy.call is None:
                return PredictedAction(call=None, verified=False, attempts=1, reason=NO_ACTION,
                                       rejected=[Rejection(call=greedy.text, reason=greedy.reason)])
            verdicts = self._check(history, [greedy.call])
            return PredictedAction(call=greedy.call, verified=verdicts[0].allowed, attempts=1)
        verdicts = self._verdicts(history, tried)
        if not verdicts[0].allowed and self.options.max_attempts > 1:
            more = self._sample(prompt, self.options.max_attempts - 1, self.options.temperature,
                                self.options.seed + 1 + step)
            tried += more
            verdicts += self._verdicts(history, more)
        rejected: list[Rejection] = []
        for attempt, (prediction, verdict) in enumerate(zip(tried, verdicts, strict=True), start=1):
            if verdict.allowed and prediction.call is not None:
                return PredictedAction(call=prediction.call, verified=True, attempts=attempt, rejected=rejected)
            rejected.append(Rejection(call=prediction.call or prediction.text, violations=verdict.violations,
                                      reason=verdict.error or prediction.reason or "violates the preconditions"))
        if self.options.fallback == "greedy" and greedy.call is not None:
            return PredictedAction(call=greedy.call, verified=False, attempts=len(tried), rejected=rejected,
                                   reason="fallback: the greedy call, which does not satisfy the preconditions")
        return PredictedAction(call=None, verified=False, attempts=len(tried), rejected=rejected,
                               reason=f"no verified action: none of the {len(tried)} attempts is a call of an "
                               "action that satisfies the preconditions (see rejected)")

    def _verdicts(self, history: str, predictions: Sequence[Prediction]) -> list[CallVerdict]:
        """One sandbox call for all action calls; non-actions get a refusal without running anything."""
        calls = [p.call for p in predictions if p.call is not None]
        checked = iter(self._check(history, calls))
        return [next(checked) if p.call is not None else CallVerdict(call=p.text, allowed=False)
                for p in predictions]

"""Next actions, in the mode the request picks: the paper's Algorithm 1 (`sample`) or `constrained`.

`sample`, "Sample Next Action with Verification": greedy first; if its program fails the preconditions, random
samples until one runs, up to `max_attempts`; otherwise "no verified action" (`call: null`, with every rejected
attempt and why), or, only when the caller asked for it (`options.fallback: "greedy"`), the greedy call with
`verified: false`. A line that is not a call of one of the agent's actions (a user act, free text) is never
returned as an action. The random samples are drawn as one batch and verified in one sandbox call, then read in
order: the same outcome as drawing them one at a time, at a fraction of the cost.

`constrained` (precond/engine/acting/constrained.py): every call the agent could make is judged in one sandbox call and
the
model chooses among the allowed ones by likelihood; no allowed call is answered as such (`nothing_allowed`).
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from precond.engine.acting import constrained
from precond.engine.candidates import prompting
from precond.engine.spec import Spec
from precond.programs.checks import instance_classes
from precond_client.schemas import (
    MAX_THOUGHT_CHARS,
    AllowedCall,
    CallVerdict,
    NextActionRequest,
    PredictedAction,
    Rejection,
    RuleStatus,
    rule_status,
)
from precond_client.schemas.errors import Cancelled, InvalidInput

if TYPE_CHECKING:
    from precond.engine.models import CodeModel

NO_ACTION = "no action: the model's line is not a call of an action function"
THOUGHT = "# think: "
THOUGHT_TOKENS = 64
"""A thought's length bound in tokens (ReAct's hand-written ALFWorld thoughts are 10 to 60)."""
MAX_THOUGHTS = 3
VerifyFn = Callable[[Spec, dict[str, list[str]], str, list[str]], list[CallVerdict]]


@dataclass(frozen=True)
class Prediction:
    text: str
    call: str | None
    reason: str | None = None
    action: str | None = None


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
    return Prediction(text, ast.unparse(call), action=name)


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
        # a fine-tuned policy's own calls count like a demonstration's for the argument values it may choose
        known = [ast.parse("\n".join(model.known_calls))] if model.known_calls else []
        self.demo_trees = [ast.parse(s) for s in request.demonstrations] + known
        classes = {m.cls for m in spec.methods.values()}
        self.receivers = instance_classes([*self.demo_trees, ast.parse(self.history)], classes)
        self.actors = instance_classes([ast.parse(self.history)], classes)
        acting = sorted({spec.methods[a].cls for a in self.actions if a in spec.methods})
        if not set(acting) & set(self.actors.values()):
            raise InvalidInput(
                f"the history creates no object of the acting class ({', '.join(acting)}), so there is no one to "
                "act: start it with the setup statements (e.g. `user = USER()`, `system = SYSTEM(user)`), or send "
                "it as a list of events, which adds them", field="history")

    def run(self, progress: Callable[[str, int, int], None]) -> list[PredictedAction]:
        history = self.history
        out: list[PredictedAction] = []
        one = self._constrained if self.options.mode == "constrained" else self._one
        for step in range(self.options.max_actions):
            if self.cancelled():
                raise Cancelled("job cancelled")
            progress("predict", step, self.options.max_actions)
            thoughts: list[str] = []
            if self.options.think:
                history, thoughts = self._think(history)
            predicted = one(history, step)
            if predicted is None:
                break
            out.append(self._stated(predicted).model_copy(update={"thoughts": thoughts}))
            if predicted.call is None:
                break  # no action to continue the turn from
            history = append_line(history, predicted.call)
        progress("done", len(out), len(out))
        return out

    def _think(self, history: str) -> tuple[str, list[str]]:
        """ReAct: the model's greedy `# think:` line after the history, then as many more as it writes before an
        action (ReAct's demonstrations start with two: the plan, then where to look first), at most
        MAX_THOUGHTS; the history with them, and them. Each is kept to printable characters: no line break in
        the model's text can end the comment, so what follows the history stays inert comment lines."""
        indent = constrained.indentation(history)
        text = self._line(history, indent + THOUGHT.rstrip())
        thoughts: list[str] = []
        while True:
            thought = "".join(ch for ch in text if ch.isprintable()).strip()[:MAX_THOUGHT_CHARS]
            thoughts.append(thought)
            history = append_line(history, f"{THOUGHT}{thought}")
            following = self._line(history, indent).strip() if len(thoughts) < MAX_THOUGHTS else ""
            if not following.startswith("#"):
                return history, thoughts
            text = following.lstrip("#").strip().removeprefix("think:")

    def _line(self, history: str, suffix: str) -> str:
        """The model's greedy continuation of `suffix` after the history, to the end of the line."""
        from precond.engine.models import Sampling

        sampling = Sampling(0.0, 1.0, THOUGHT_TOKENS, self.options.seed)
        return self.model.complete(self._prompt(history), [suffix], 1, sampling, "line", self.cancelled)[0][0]

    def _prompt(self, history: str) -> str:
        return prompting.next_action_prompt(
            self.spec, self.request.preconditions, self.request.demonstrations, history,
            self.options.preconditions_in_prompt,
        )

    def _stated(self, predicted: PredictedAction) -> PredictedAction:
        """The prediction with what the rule of each judged call's action rests on (`rule_status`): a call
        allowed because nothing is known about its action says so, as a verdict of `check-actions` does."""
        rejected = [r.model_copy(update={"rule_status": self._status(r.action)}) for r in predicted.rejected]
        return predicted.model_copy(update={"rule_status": self._status(predicted.action), "rejected": rejected})

    def _status(self, action: str | None) -> RuleStatus | None:
        if action is None:
            return None
        return rule_status(self.request.preconditions.get(action, []), self.request.decided.get(action, {}))

    def _held(self, action: str | None, verdict: CallVerdict) -> list[str]:
        """The action's rules that hold: all but the violated ones, none when the call could not be judged."""
        if action is None or verdict.error is not None:
            return []
        return [rule for rule in self.request.preconditions.get(action, []) if rule not in verdict.violations]

    def _sample(self, prompt: str, n: int, temperature: float, seed: int) -> list[Prediction]:
        from precond.engine.models import Sampling

        sampling = Sampling(temperature, 0.95, self.options.max_new_tokens, seed)
        texts = self.model.complete(prompt, [""], n, sampling, "line", self.cancelled)[0]
        return [classify(t, self.receivers, self.actions) for t in texts]

    def _check(self, history: str, calls: list[str]) -> list[CallVerdict]:
        return self.verify(self.spec, self.request.preconditions, history, calls) if calls else []

    def _allowed_of(self, history: str) -> list[AllowedCall] | None:
        """Mode 'sample' with `return_allowed`: the allowed set, judged like the constrained mode's (unscored)."""
        if not self.options.return_allowed:
            return None
        candidates = self._candidates(history)
        return [AllowedCall(call=v.call) for v in self._check(history, candidates.calls) if v.allowed]

    def _one(self, history: str, step: int) -> PredictedAction | None:
        prompt = self._prompt(history)
        greedy = self._sample(prompt, 1, 0.0, self.options.seed)[0]
        if greedy.call is None and step > 0:
            return None  # the model hands the turn back: no further action this turn
        tried = [greedy]
        if not self.options.verify:
            if greedy.call is None:
                return PredictedAction(call=None, verified=False, attempts=1, reason=NO_ACTION,
                                       rejected=[Rejection(call=greedy.text, reason=greedy.reason)])
            verdicts = self._check(history, [greedy.call])
            return PredictedAction(call=greedy.call, action=greedy.action, verified=verdicts[0].allowed, attempts=1,
                                   held=self._held(greedy.action, verdicts[0]),
                                   allowed=self._allowed_of(history))
        verdicts = self._verdicts(history, tried)
        if not verdicts[0].allowed and self.options.max_attempts > 1:
            more = self._sample(prompt, self.options.max_attempts - 1, self.options.temperature,
                                self.options.seed + 1 + step)
            tried += more
            verdicts += self._verdicts(history, more)
        allowed = self._allowed_of(history)
        rejected: list[Rejection] = []
        for attempt, (prediction, verdict) in enumerate(zip(tried, verdicts, strict=True), start=1):
            if verdict.allowed and prediction.call is not None:
                return PredictedAction(call=prediction.call, action=prediction.action, verified=True,
                                       attempts=attempt, rejected=rejected,
                                       held=self._held(prediction.action, verdict), allowed=allowed)
            rejected.append(_rejection(prediction.call or prediction.text, verdict, prediction.reason,
                                       prediction.action))
        if self.options.fallback == "greedy" and greedy.call is not None:
            return PredictedAction(call=greedy.call, action=greedy.action, verified=False, attempts=len(tried),
                                   rejected=rejected,
                                   held=self._held(greedy.action, verdicts[0]), allowed=allowed,
                                   reason="fallback: the greedy call, which does not satisfy the preconditions")
        return PredictedAction(call=None, verified=False, attempts=len(tried), rejected=rejected, allowed=allowed,
                               reason=f"no verified action: none of the {len(tried)} attempts is a call of an "
                               "action that satisfies the preconditions (see rejected)")

    def _verdicts(self, history: str, predictions: Sequence[Prediction]) -> list[CallVerdict]:
        """One sandbox call for all action calls; non-actions get a refusal without running anything."""
        calls = [p.call for p in predictions if p.call is not None]
        checked = iter(self._check(history, calls))
        return [next(checked) if p.call is not None else CallVerdict(call=p.text, allowed=False)
                for p in predictions]

    # ---- mode 'constrained' -------------------------------------------------------------------------
    def _candidates(self, history: str) -> constrained.Candidates:
        trees = [*self.demo_trees, ast.parse(history)]
        values, every = constrained.argument_values(self.spec, trees)
        ordered = [a for a in self.spec.methods if a in self.actions]
        return constrained.enumerate_calls(self.spec, ordered, self.actors, values, every)

    def _constrained(self, history: str, step: int) -> PredictedAction | None:
        candidates = self._candidates(history)
        verdicts = self._check(history, candidates.calls)
        allowed = [v.call for v in verdicts if v.allowed]
        rejected = [_rejection(v.call, v, None, candidates.action[v.call]) for v in verdicts if not v.allowed]
        cut = (f"; argument values were cut to {constrained.MAX_PER_ACTION} calls per action, "
               f"{constrained.MAX_ENUMERATED} in all" if candidates.truncated else "")
        if not allowed:
            return PredictedAction(
                call=None, verified=False, attempts=len(verdicts), rejected=rejected, nothing_allowed=True,
                allowed=[] if self.options.return_allowed else None,
                reason=f"nothing allowed: none of the {len(verdicts)} calls the agent could make now satisfies "
                f"the preconditions (each is in rejected, with the precondition that fails){cut}",
            )
        if self.cancelled():
            raise Cancelled("job cancelled")
        chosen, scores, stop = self._choose(history, step, candidates, allowed)
        if stop:
            return None  # handing the turn back is likelier than any allowed action
        verdict = next(v for v in verdicts if v.call == chosen)
        return PredictedAction(
            call=chosen, action=candidates.action[chosen], verified=True, attempts=len(verdicts), rejected=rejected,
            held=self._held(candidates.action[chosen], verdict),
            allowed=[AllowedCall(call=c, score=scores.get(c)) for c in allowed]
            if self.options.return_allowed else None,
            reason=f"chosen by likelihood among {len(allowed)} allowed calls{cut}",
        )

    def _choose(self, history: str, step: int, candidates: constrained.Candidates, allowed: list[str]
                ) -> tuple[str, dict[str, float], bool]:
        """The likeliest allowed line, the scores of its last pass, and whether ending the turn is likelier.

        `choose_by: action` (default), and always beyond MAX_LINES allowed calls (ALFWorld's `take(obj, recep)`
        has hundreds of allowed pairs): passes over the same prompt (its cache reused as is) choose the action's
        head first, then each argument in turn among the allowed calls that agree with those chosen so far:
        greedy decoding at the grain of an action, then of an argument, restricted to what is allowed. Whole
        lines compared by likelihood favour the short ones (`system.NOTIFY_SUCCESS()` over every
        `system.REQUEST('slot')`); compared at the action, each action's mass is not split among its arguments.
        `choose_by: line`: one `score` pass holds every allowed line and the heads that decide whether the turn
        ends (`ends_turn`); the likeliest line wins.
        """
        indent = constrained.indentation(history)
        prompt = self._prompt(history)
        turn = constrained.turn_heads(self.spec, self.actors, self.actions) if step > 0 else None
        ends = turn.all if turn else []
        if self.options.choose_by == "line" and len(allowed) <= constrained.MAX_LINES:
            scores = self.model.score(prompt, [f"{indent}{c}\n" for c in allowed] + [indent + h for h in ends],
                                      self.cancelled)
            full = dict(zip(allowed, scores[: len(allowed)], strict=True))
            stop = turn is not None and constrained.ends_turn(turn, dict(zip(ends, scores[len(allowed):],
                                                                             strict=True)))
            return max(allowed, key=lambda c: full[c]), full, stop
        heads = list(dict.fromkeys(candidates.head[c] for c in allowed))
        bare = [h.rstrip("(") for h in heads]
        longer = constrained.extensions(bare, [h.rstrip("(") for h in candidates.head.values()])
        first = list(dict.fromkeys([*bare, *(o for os in longer.values() for o in os), *ends]))
        scored = dict(zip(first, self.model.score(prompt, [indent + h for h in first], self.cancelled),
                          strict=True))
        own = {b: (constrained.own_mass(b, scored, longer), scored[b]) for b in bare}
        best = max(heads, key=lambda h: own[h.rstrip("(")])
        if turn is not None and constrained.ends_turn(turn, scored):
            return best, {}, True
        return self._arguments(prompt, indent, best, candidates, [c for c in allowed if candidates.head[c] == best])

    def _arguments(self, prompt: str, indent: str, head: str, candidates: constrained.Candidates,
                   calls: list[str]) -> tuple[str, dict[str, float], bool]:
        """One action's allowed call, chosen argument by argument (see `_choose`)."""
        full: dict[str, float] = {}
        chosen: list[constrained.Scalar] = []
        arity = len(candidates.args[calls[0]])
        for k in range(arity):
            calls = [c for c in calls if list(candidates.args[c][:k]) == chosen]
            options = list(dict.fromkeys(candidates.args[c][k] for c in calls))[: constrained.MAX_SCORED]
            if len(options) > 1:
                texts = constrained.argument_texts(indent + head, chosen, options, k == arity - 1)
                values = dict(zip(options, self.model.score(prompt, texts, self.cancelled), strict=True))
                if k == arity - 1:
                    full = {c: values[candidates.args[c][k]] for c in calls if candidates.args[c][k] in values}
                options = [max(options, key=lambda v: values[v])]
            chosen.append(options[0])
        return next(c for c in calls if list(candidates.args[c]) == chosen), full, False


def _rejection(call: str, verdict: CallVerdict, reason: str | None, action: str | None) -> Rejection:
    return Rejection(call=call, action=action, violations=verdict.violations,
                     reason=verdict.error or reason or "violates the preconditions")

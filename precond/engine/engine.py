"""The paper's two procedures, in-process: precondition inference and verified next-action sampling.

Everything untrusted (spec, demonstrations, model output) is executed only through the sandbox; this module
decides what to run and how to read the answers. The model is loaded lazily, so model-free requests
(`enumerate`, `check`) never pay for it.
"""

from __future__ import annotations

import ast
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from precond.convert.openai import call_lines, call_schema_problems, structured_history
from precond.engine import counterexamples, judge, priors, prompting, scope
from precond.engine import guarded as guarding
from precond.engine.decisive import decisive_points
from precond.engine.enumeration import StateModel, enumerate_atoms
from precond.engine.evidence import OccurrenceIndex, thin, too_few
from precond.engine.freshness import writes_at
from precond.engine.left_out import Traced, trace_judgeable
from precond.engine.library import Library, shipped
from precond.engine.next_action import NextActionPlanner
from precond.engine.notices import rule_warnings
from precond.engine.parsing import parse_samples
from precond.engine.ranking import (
    Cluster,
    cluster,
    informative,
)
from precond.engine.report import UNSEEN_RULE, Proposals, Ranked, listed, report_of
from precond.engine.runnable import drop_unrunnable
from precond.engine.selection import Inference, select_rules
from precond.engine.shared_rules import shared
from precond.engine.spec import (
    Spec,
    as_error,
    call_actions,
    check_calls,
    check_preconditions,
    parse_source,
    parse_spec,
    remembered_spec,
    render_program,
    resolve_actions,
    skip_statements,
)
from precond.engine.tool_conditions import separating, tool_atoms, tool_class
from precond.engine.tool_relations import relations
from precond.engine.work import WorkBudget, points_of
from precond.programs import checks
from precond.sandbox.types import (
    TIMED_OUT,
    BrokenRule,
    EvaluateResult,
    LimitExceeded,
    Point,
    ProgramError,
    SandboxCancelled,
    SandboxCrashed,
    SandboxUnavailable,
    TraceResult,
)
from precond_client.schemas.api import (
    MAX_CALL_CHARS,
    Blocked,
    CallVerdict,
    CheckRequest,
    CheckResponse,
    Decided,
    HistoryEvent,
    InferOptions,
    InferRequest,
    InferResponse,
    ModelInfo,
    NextActionRequest,
    NextActionResponse,
    ValidateResponse,
    rule_status,
)
from precond_client.schemas.errors import (
    Cancelled,
    InvalidInput,
    InvalidProgram,
    ModelUnavailable,
    ResourceLimit,
    SandboxFailure,
)

if TYPE_CHECKING:
    from precond.engine.models import CodeModel
    from precond.engine.models.backend import Weights
    from precond.sandbox import Sandbox

ProgressFn = Callable[[str, int, int], None]
ModelLoader = Callable[[], "CodeModel"]
WeightsLoader = Callable[[], "Weights"]
T = TypeVar("T")

SANDBOX_FIELDS = {"spec": "spec", "history": "history", "preconditions": "preconditions"}
MODEL_WAIT_POLL_S = 0.1
"""How often a job waiting for the model's load checks whether it was cancelled."""


def broken_text(history: str, broken: BrokenRule | None) -> str | None:
    """Where a history broke a rule, in words: the line, its call, the action and the rules that did not hold."""
    if broken is None:
        return None
    lines = history.splitlines()
    call = lines[broken.line - 1].strip() if 0 < broken.line <= len(lines) else "?"
    rules = ", ".join(f"`{rule}`" for rule in broken.rules)
    return (f"history, line {broken.line}: {call}: {broken.action}'s rule{'s' if len(broken.rules) > 1 else ''} "
            f"{rules} did not hold")


def _no_progress(phase: str, done: int, total: int) -> None:
    return None


def _never() -> bool:
    return False


def sandbox_call(fn: Callable[..., T], *args: object, **kwargs: object) -> T:
    """Turn the sandbox's errors about untrusted input into the API's user-facing errors."""
    try:
        return fn(*args, **kwargs)
    except ProgramError as exc:
        where = f"demonstrations[{exc.index}]" if exc.where == "demonstration" else SANDBOX_FIELDS.get(exc.where)
        raise InvalidProgram(str(exc), field=where) from exc
    except LimitExceeded as exc:
        field = "demonstrations" if exc.limit == "work" else None  # points grow with demonstrations × arguments
        raise ResourceLimit(f"untrusted code hit the sandbox's {exc.limit} limit: {exc.message}", field=field) from exc
    except SandboxCancelled as exc:
        raise Cancelled("job cancelled") from exc
    except (SandboxCrashed, SandboxUnavailable) as exc:
        raise SandboxFailure(f"the sandbox failed, not the request (try again): {exc}") from exc


class Timer:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - start, 4)


class Engine:
    def __init__(self, sandbox: Sandbox, model_loader: ModelLoader | None = None,
                 weights_loader: WeightsLoader | None = None, policy: str | None = None) -> None:
        """`weights_loader` gives a fresh, trainable copy of the base model (policy training); `policy` is the
        trained policy this engine's model is (`options.policy` of the next actions it answers), None the base."""
        self._sandbox = sandbox
        self._loader = model_loader
        self._weights = weights_loader
        self._policy = policy
        self._model: CodeModel | None = None
        self._lock = threading.Lock()
        self.library: Library = shipped()
        """The rule library priors come from (engine.library); the evaluation swaps in one built without the
        domain it scores."""

    @property
    def sandbox(self) -> Sandbox:
        return self._sandbox

    @property
    def model_loaded(self) -> bool:
        return self._model is not None

    @property
    def trains(self) -> bool:
        """Whether a code model to train policies on is configured (a worker trains them in a process of its own,
        precond/worker/training_process.py, with the same settings)."""
        return self._weights is not None

    def model(self, cancelled: Callable[[], bool] = _never) -> CodeModel:
        """Load once, on first use; concurrent first uses wait for the same load, each stopping its wait when
        its job is cancelled (a job taken while the worker still loads its model is cancelled at once)."""
        while not self._lock.acquire(timeout=MODEL_WAIT_POLL_S):
            self._check_cancel(cancelled)
        try:
            if self._model is None:
                if self._loader is None:
                    raise ModelUnavailable("no code model is configured for this worker")
                self._model = self._loader()
            return self._model
        finally:
            self._lock.release()

    # ---- trained policies (behaviour cloning) ------------------------------------------------------
    def with_policy(self, adapter: Path, policy: str | None) -> Engine:
        """An engine on the same sandbox whose model is this one's with the adapter at `adapter` beside the weights
        it changes, unmerged (`backend.with_adapter`); it answers next actions naming `policy` (None: naming none,
        the command line's `--adapter`)."""
        from precond.engine.models.backend import with_adapter

        adapted = with_adapter(self.model(), adapter)
        return Engine(self._sandbox, lambda: adapted, policy=policy)

    # ---- precondition inference -------------------------------------------------------------------
    def infer(
        self,
        request: InferRequest,
        progress: ProgressFn = _no_progress,
        cancelled: Callable[[], bool] = _never,
    ) -> InferResponse:
        with self._sandbox.cancel_when(cancelled):
            return self._infer(request, progress, cancelled)

    def _infer(self, request: InferRequest, progress: ProgressFn, cancelled: Callable[[], bool]) -> InferResponse:
        timer = Timer()
        spec = parse_spec(request.spec)
        actions = resolve_actions(spec, request.actions)
        demo_trees = [parse_source(d, f"demonstrations[{i}]") for i, d in enumerate(request.demonstrations)]
        demos = list(request.demonstrations)
        labelled = counterexamples.read(spec, request.counterexamples, demos, actions) \
            if request.counterexamples else None
        prior = priors.collect(request.options, spec, actions, demos, self.library)
        guarded = _guarded(spec, actions, request.options)
        progress("trace", 0, 1)
        with timer.phase("trace"):
            traced = sandbox_call(trace_judgeable, self._sandbox, spec.source, demos, scope.current())
        trace = traced.trace
        if traced.left_out:  # too large to judge: each is empty from here on, and named in the warnings
            request, demos = _without(request, traced), traced.demonstrations
            demo_trees = [parse_source(d, f"demonstrations[{i}]") for i, d in enumerate(demos)]
            labelled = counterexamples.read(spec, request.counterexamples, demos, actions) \
                if request.counterexamples else None
        _refuse_no_evidence(actions, trace)
        judged_at = _judged_at(spec, actions, trace)
        enumerated = Proposals()
        stopped: dict[str, str] = {}
        policy: dict[str, set[str]] = {}
        if "enumerate" in request.options.generators:
            with timer.phase("enumerate"):
                labelled_trees = [parse_source(p, "counterexamples") for p in labelled.programs] if labelled else []
                stopped = self._enumerate(spec, actions, demo_trees + labelled_trees, trace, enumerated,
                                          request.options.now, policy, judged_at, len(demo_trees))
        writes = writes_at(spec, trace) if request.options.ranking == "cautious" else {}
        prompted = _prompted(actions, trace, request.options)
        settled = [a for a in actions if a not in prompted]
        proposals = Proposals()
        model_info: ModelInfo | None = None
        first: EvaluateResult | None = None
        if "model" in request.options.generators and prompted:
            known: dict[str, list[str]] = {}
            if settled and request.options.show_rules:  # the evidence decides these first; the model reads them
                found = _proposed(settled, enumerated, prior)
                with timer.phase("validate"):
                    first = sandbox_call(self._sandbox.evaluate, spec.source, demos,
                                         {a: list(found.source.get(a, {})) for a in settled},
                                         {a: judged_at[a] for a in settled if a in judged_at}, scope=scope.current())
                with timer.phase("rank"):
                    known = _known_rules(spec, prompted, select_rules(
                        settled, Inference(trace, first, found, request.options, writes, prior), guarded))
                self._check_cancel(cancelled)
            with timer.phase("generate"):
                model_info = self._generate(spec, actions, prompted, request, proposals, progress, cancelled, known)
        proposals = _proposed(actions, enumerated, prior, proposals)
        self._check_cancel(cancelled)
        progress("validate", 0, 1)
        with timer.phase("validate"):
            rest = [a for a in actions if first is None or a not in first.results]
            evaluated = _merged(first, sandbox_call(self._sandbox.evaluate, spec.source, demos,
                                                    {a: list(proposals.source.get(a, {})) for a in rest},
                                                    {a: judged_at[a] for a in rest if a in judged_at},
                                                    scope=scope.current()))
        unseen = {a: not trace.actions[a].occurrences for a in actions}
        unrunnable: dict[str, dict[str, str]] = {}
        if any(unseen.values()):
            evaluated, unrunnable = drop_unrunnable(spec, StateModel(spec, demo_trees), actions, evaluated, unseen)
        progress("rank", 0, 1)
        with timer.phase("rank"):
            ranked = select_rules(actions, Inference(trace, evaluated, proposals, request.options, writes, prior),
                                  guarded)
        if request.options.judge:
            with timer.phase("judge"):
                ranked = self._judge(spec, actions, demos, trace, evaluated, ranked, request.options)
        separated: dict[str, counterexamples.Separation] = {}
        if labelled is not None:
            with timer.phase("counterexamples"):
                separated = self._separate(spec, labelled, trace, evaluated, ranked, policy, demos)
            ranked = {**ranked, **{a: s.ranked for a, s in separated.items()}}
        chosen = {a: [c.representative.expression for c in ranked[a].chosen] for a in actions}
        if request.options.unseen == "refuse":  # unless the code model's zero-shot guess, or a call labelled
            shown = {c.action for c in labelled.cases if c.verdict == "allow"} - {  # 'allow' and none 'refuse'
                c.action for c in labelled.cases if c.verdict == "refuse"} if labelled else set()
            unshown = {a for a, s in separated.items() if s.unshown}
            chosen.update({a: [UNSEEN_RULE] for a in guarded if (not trace.actions[a].occurrences or a in unshown)
                           and not chosen[a] and a not in shown})
        with timer.phase("verify"):
            exempt = _exceptions_of(chosen, ranked)
            for separation in separated.values():
                for point in separation.exempt:
                    exempt.setdefault(point.demo, set()).add(point.position)
            program, preconditions, dropped = self._verified_program(spec, chosen, demos, exempt)
        response = report_of(actions, proposals, ranked, preconditions, dropped, timer.seconds, trace)
        for action, separation in separated.items():
            for rule, kept in response.evidence[action].items():
                response.evidence[action][rule] = kept.model_copy(update={
                    "refuses": separation.refuses.get(rule, []),
                    "refuses_allowed": separation.refuses_allowed.get(rule, [])})
        occurrences = {a: trace.actions[a].occurrences for a in actions}
        decided = {a: {rule: ranked[a].decided.get(rule, "unseen" if rule == UNSEEN_RULE else "established")
                       for rule in preconditions[a]} for a in actions}
        warnings = rule_warnings(actions, occurrences, preconditions, decided, model_info is not None,
                                 request.options, prior.dropped)
        for action, dropped_here in unrunnable.items():
            listed_here = "; ".join(f"`{e}` ({why})" for e, why in list(dropped_here.items())[:3])
            warnings[action] = "; ".join(w for w in (warnings.get(action), (
                f"{len(dropped_here)} candidate(s) dropped: they raise on the spec's state: {listed_here}")) if w)
        for action, slow in _timed_out(evaluated).items():
            warnings[action] = "; ".join(w for w in (warnings.get(action), (
                f"{slow} candidate(s) dropped: they ran out of time in the sandbox (SANDBOX_TIMEOUT_S), judged "
                f"alone too; the others were judged")) if w)
        for action, separation in separated.items():
            if separation.conflicts:
                warnings[action] = "; ".join(w for w in (warnings.get(action), *separation.conflicts) if w)
            if separation.unrefused:
                warnings[action] = "; ".join(w for w in (warnings.get(action), _unrefused(
                    separation.unrefused, preconditions[action] == [UNSEEN_RULE])) if w)
        default = "" if request.options.guarded is not None else guarding.note(guarded)
        for action in actions:  # a search cut at its bound, or the rules an act does not keep, say so
            unrefused = action not in guarded and not preconditions[action] and unseen[action]
            said = ranked[action].unguarded or (guarding.UNREFUSED if unrefused else "")
            unguarded = "; ".join(w for w in (said, default) if said and w)
            cuts = (warnings.get(action), stopped.get(action), ranked[action].search, ranked[action].behind, unguarded)
            if any(cuts[1:]):
                warnings[action] = "; ".join(w for w in cuts if w)
        warnings.update({f"demonstrations[{i}]": why for i, why in traced.left_out.items()})
        progress("done", 1, 1)
        return InferResponse(
            preconditions=preconditions, program=program, stats=response.stats,
            candidates=listed(response.candidates, request.options.candidates),
            model=model_info, warnings=warnings, evidence=response.evidence,
        )

    def _separate(self, spec: Spec, labelled: counterexamples.Labelled, trace: TraceResult,
                  evaluated: EvaluateResult, ranked: Mapping[str, Ranked], policy: Mapping[str, set[str]],
                  demos: Sequence[str]) -> dict[str, counterexamples.Separation]:
        """Each labelled action's rules against its labelled calls (`engine.counterexamples`): every judged
        condition is judged again at the labelled calls of the runs given as programs."""
        try:
            runs = sandbox_call(self._sandbox.trace, spec.source, labelled.programs, scope=scope.current()) \
                if labelled.programs else None
        except InvalidProgram as exc:
            raise InvalidProgram(str(exc).replace("demonstration", "counterexample run"),
                                 field="counterexamples") from exc
        where = counterexamples.points(labelled, runs) if runs is not None else {}
        separated = {}
        for action in sorted(labelled.actions()):
            cases = where.get(action, [])
            results: dict[str, Any] = {}
            order: list[Any] = [p for _, p in cases]
            if cases:
                expressions = _separable(ranked[action], policy.get(action))
                judged = sandbox_call(self._sandbox.evaluate, spec.source, labelled.programs, {action: expressions},
                                      {action: order}, scope=scope.current())
                results = {r.expression: r for r in judged.results.get(action, ())}
                order = list(judged.points.get(action, order))
            separated[action] = counterexamples.separate(
                action, ranked[action], evaluated.points.get(action, ()), trace.actions[action].occurrences,
                counterexamples.demonstrated_points(labelled, trace, action), cases, results, order,
                policy.get(action), counterexamples.task_of(labelled, demos))
        unlabelled = {a: (ranked[a], OccurrenceIndex.of(evaluated.points.get(a, ()), trace.actions[a].occurrences))
                      for a in policy if a not in separated and a in ranked and trace.actions[a].occurrences}
        return shared(separated, unlabelled)

    def _generate(
        self,
        spec: Spec,
        actions: list[str],
        prompted: list[str],
        request: InferRequest,
        proposals: Proposals,
        progress: ProgressFn,
        cancelled: Callable[[], bool],
        known: Mapping[str, Sequence[str]],
    ) -> ModelInfo:
        """Samples for the `prompted` actions, in prompts that show every action's stub (the same prompt
        whichever actions are asked about) and, before the asked one, the rules `known` of its class's other
        actions."""
        from precond.engine.models import Sampling

        options = request.options
        model = self.model(cancelled)
        windows = prompting.demo_windows(
            len(request.demonstrations), options.prompts_per_action, options.demonstrations_per_prompt
        )
        suffixes = [prompting.inference_suffix(spec, a, known) for a in prompted]
        for index, window in enumerate(windows):
            self._check_cancel(cancelled)
            progress("generate", index, len(windows))
            prefix = prompting.inference_prefix(spec, actions, [request.demonstrations[i] for i in window])
            sampling = Sampling(options.temperature, options.top_p, options.max_new_tokens, options.seed + index)
            samples = model.complete(prefix, suffixes, options.samples_per_prompt, sampling, "statement", cancelled)
            for action, texts in zip(prompted, samples, strict=True):
                parsed = parse_samples(texts)
                proposals.add(action, parsed.assertions, "model", parsed.sampled, parsed.votes)
        progress("generate", len(windows), len(windows))
        return model.info

    def _enumerate(
        self, spec: Spec, actions: list[str], demo_trees: list[ast.Module], trace: TraceResult, proposals: Proposals,
        now: str | None = None, policy: dict[str, set[str]] | None = None,
        judged_at: Mapping[str, Sequence[Point]] | None = None, demonstrated: int | None = None,
    ) -> dict[str, str]:
        """Adds the enumerator's atoms, each action's cut to the work budget; the report line of each cut one.
        `policy` gets, for a tool spec's actions, the conditions over results and arguments (`tool_conditions`):
        the ones labelled calls are separated by. `judged_at`: the actions judged at fewer points than their
        default grid (`decisive`), whose budget is counted on those; `demonstrated`: how many of `demo_trees` are
        demonstrations (the rest are runs of labelled calls)."""
        budget = WorkBudget(self._sandbox.limits.max_points)
        state = StateModel(spec, demo_trees)
        state.tool_facts.now, state.tool_facts.demonstrated = now, demonstrated
        stopped: dict[str, str] = {}
        for action in actions:
            info = trace.actions[action]
            n_points = len(judged_at[action]) if judged_at and action in judged_at else points_of(trace, info)
            found = enumerate_atoms(state, info, spec.methods[action].cls, budget.enumerated(n_points))
            proposals.add(action, found.atoms, "enumerate", len(found.atoms))
            if policy is not None and spec.methods[action].cls == state.tool_class:
                name = spec.methods[action].name
                policy[action] = separating(tool_atoms(state.tool_facts, name, info.params)
                                            + relations(state.tool_facts, name, info.params))
            if found.cut:
                stopped[action] = budget.stopped(len(found.atoms), n_points)
        return stopped


    def _judge(self, spec: Spec, actions: list[str], demos: list[str], trace: TraceResult,
               evaluated: EvaluateResult, ranked: dict[str, Ranked], options: InferOptions) -> dict[str, Ranked]:
        """Let the code model settle what the evidence left open (`engine.judge`), one question per action."""
        questions = [q for a in actions if not ranked[a].transferred
                     and (q := _question(a, ranked[a], trace, len(evaluated.points.get(a, ())), options)) is not None]
        if not questions:
            return ranked
        model = self.model()
        rules = {a: [c.representative.expression for c in ranked[a].chosen] for a in actions}
        judged = dict(ranked)
        for q in questions:
            verdict = judge.decide(model, spec, actions, demos[0] if demos else "", rules, q)
            r = ranked[q.action]
            chosen = list(r.chosen) if q.kind == "phase" else []
            chosen += [Cluster((c,)) for c in r.valid if c.expression == verdict.adopted][:1]
            reasons = {**r.reasons, **{e: verdict.describe(e) for e in q.options if e in q.open}}
            decided: dict[str, Decided] = {
                e: d for e, d in r.decided.items() if any(c.representative.expression == e for c in chosen)}
            if verdict.adopted:
                decided[verdict.adopted] = "zero-shot"
            judged[q.action] = Ranked(r.results, r.valid, r.clusters, chosen, reasons, r.evidence, r.verdicts,
                                      decided)
        return judged

    def _verified_program(
        self, spec: Spec, chosen: dict[str, list[str]], demos: list[str],
        exempt: Mapping[int, set[int]] | None = None,
    ) -> tuple[str, dict[str, list[str]], dict[str, dict[str, str]]]:
        """The spec with the kept assertions, run on every demonstration; assertions that fail together are dropped.

        `exempt` are the steps (demonstration -> main-body positions) that kept rules refuse by design: the
        exceptions evidence-weighted validation accepted. They are skipped (the statement becomes `pass` on
        the same lines) so that a tolerated slip is not mistaken for a conflict; an inferred action is a stub,
        so skipping its call leaves the state the later steps see as it was.

        Each assertion was validated alone, but together they can disagree: one action's assertion may change
        the state another reads (subscripting a defaultdict inserts the key, so `len(d) == 1` later fails).
        The assertion that fails is dropped (it is the one that read state its validation never saw) until
        the program runs. Returns the program, the preconditions it holds, and per action the dropped
        assertions with the reason.
        """
        preconditions = {action: list(kept) for action, kept in chosen.items()}
        dropped: dict[str, dict[str, str]] = {}
        demos = [skip_statements(d, (exempt or {}).get(i, set())) for i, d in enumerate(demos)]
        while True:
            failure = self._failure(spec, preconditions, demos)
            if failure is None:
                return render_program(spec, preconditions), preconditions, dropped
            action = _action_at(spec, demos[failure.index or 0], failure.line or 0, preconditions)
            if failure.where != "demonstration" or action is None:
                raise InvalidProgram(str(failure), field=f"demonstrations[{failure.index}]")
            kept = preconditions[action]
            culprit = next(
                (i for i in reversed(range(len(kept)))
                 if not _same_place(self._failure(spec, {**preconditions, action: kept[:i] + kept[i + 1:]}, demos),
                                    failure)),
                len(kept) - 1,
            )
            dropped.setdefault(action, {})[kept.pop(culprit)] = (
                f"dropped: fails with the other kept assertions (demonstrations[{failure.index}], line {failure.line})"
            )

    def _failure(self, spec: Spec, preconditions: dict[str, list[str]], demos: list[str]) -> ProgramError | None:
        try:
            sandbox_call(self._sandbox.trace, render_program(spec, preconditions), demos, scope=scope.current())
        except InvalidProgram as exc:
            if isinstance(exc.__cause__, ProgramError):
                return exc.__cause__
            raise
        return None

    # ---- next action (Algorithm 1) ------------------------------------------------------------------
    def next_action(
        self,
        request: NextActionRequest,
        progress: ProgressFn = _no_progress,
        cancelled: Callable[[], bool] = _never,
    ) -> NextActionResponse:
        if request.options.policy != self._policy:  # the worker picks the engine of the named policy
            raise InvalidInput(f"this engine serves {self._policy or 'the base model'}, not "
                               f"{request.options.policy}", field="options.policy")
        spec = parse_spec(_spec_of(request))
        check_preconditions(spec, request.preconditions)
        request = request.model_copy(update={"history": history_program(spec.source, request.history)})
        for i, demo in enumerate(request.demonstrations):
            parse_source(demo, f"demonstrations[{i}]")
        planner = NextActionPlanner(spec, request, self.model(cancelled), self._verify, cancelled)
        with self._sandbox.cancel_when(cancelled):
            violation = self._history_violation(spec, request.preconditions, planner.history)
            actions = planner.run(progress)
        return NextActionResponse(actions=actions, mode=request.options.mode, history_violation=violation,
                                  model=self.model().info)

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

    # ---- check ------------------------------------------------------------------------------------
    def check(self, request: CheckRequest, screened: bool = False) -> CheckResponse:
        """`screened`: the gateway rendered the history and the calls and ran the static screen
        (`checks.check_check`) before it queued the job, so the worker does not run it again."""
        spec = remembered_spec(scope.current(), _spec_of(request))
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
        return CheckResponse(results=[_with_status(_labelled(v, spec, request.decided), action, request)
                                      for v, action in zip(verdicts, actions, strict=True)],
                             history_violation=broken_text(history, judged.history))

    # ---- validate (a precondition set's rules against its demonstrations) ----------------------------
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

    @staticmethod
    def _check_cancel(cancelled: Callable[[], bool]) -> None:
        if cancelled():
            raise Cancelled("job cancelled")


def _raised(first_violation: str | None) -> bool:
    """The sandbox's first violation of a rule names an exception (`..., args []: AttributeError: ...`), not a
    false answer (`: assertion fails`) or a state it could not copy."""
    return bool(first_violation) and not str(first_violation).endswith(
        (": assertion fails", ": the state could not be copied"))


def _unrefused(names: Sequence[str], placeholder: bool) -> str:
    """The warning of an action whose calls labelled 'refuse' no learned rule refuses: which, and what refuses
    them instead (the placeholder of a never-demonstrated action) or that nothing does."""
    listed_here = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    then = ("the action stays refused (options.unseen: 'refuse')" if placeholder
            else "the rules allow them: review them, or write the rule")
    return (f"unseparated: {len(names)} call(s) labelled 'refuse' ({listed_here}) that no learned condition "
            f"refuses (none separates them from the calls to allow or, with none to allow, states a limit they "
            f"break); {then}")


def _labelled(verdict: CallVerdict, spec: Spec, decided: Mapping[str, Mapping[str, str]]) -> CallVerdict:
    """The verdict with how each rule that refused the call was decided (its action's label for it)."""
    if not verdict.violations or not decided:
        return verdict
    actions = [a for a in decided if a in spec.methods and f".{spec.methods[a].name}(" in verdict.call]
    labels = {rule: label for a in actions for rule, label in decided[a].items()}
    return verdict.model_copy(update={"decided": {v: labels[v] for v in verdict.violations if v in labels}})


def _with_status(verdict: CallVerdict, action: str | None, request: CheckRequest) -> CallVerdict:
    """The verdict with the action it judged and what its rule rests on (`rule_status`): allowed because the
    evidence says so, or because nothing is known."""
    if action is None:
        return verdict
    status = rule_status(request.preconditions.get(action, []), request.decided.get(action, {}))
    return verdict.model_copy(update={"action": action, "rule_status": status})


def _guarded(spec: Spec, actions: Sequence[str], options: InferOptions) -> list[str]:
    try:
        return guarding.resolve(options.guarded, actions, spec.methods)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def _spec_of(request: CheckRequest | NextActionRequest) -> str:
    if request.spec is None:
        raise InvalidInput("precondition_set is resolved by the service: send `spec` and `preconditions` here",
                           field="precondition_set")
    return request.spec


def history_program(spec: str, history: str | Sequence[HistoryEvent | dict[str, Any]]) -> str:
    """A history as the program the sandbox runs (`rendered_history`), which must parse (a 422 if not)."""
    program = rendered_history(spec, history)
    parse_source(program, "history")
    return program


def rendered_history(spec: str, history: str | Sequence[HistoryEvent | dict[str, Any]]) -> str:
    """A history as the program the sandbox runs: code as sent, or structured events (or an agent's OpenAI
    messages) rendered with literals."""
    if isinstance(history, str):
        return history
    try:
        return structured_history(spec, [e if isinstance(e, dict) else e.model_dump() for e in history],
                                  scope=scope.current())
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def _prompted(actions: Sequence[str], trace: TraceResult, options: InferOptions) -> list[str]:
    """The actions the model is asked about: all, or (`model_for: thin`, with the enumerator on to cover the
    others) those too thinly demonstrated to learn from, never demonstrated included."""
    if options.model_for == "all" or "enumerate" not in options.generators:
        return list(actions)
    return [a for a in actions if too_few(trace.actions[a].occurrences)]


def _proposed(actions: Sequence[str], enumerated: Proposals, prior: priors.Priors,
              sampled: Proposals | None = None) -> Proposals:
    """The model's samples (if any), then the enumerator's atoms, then the priors: the order that decides which
    generator a candidate is reported from and which text stands for its cluster."""
    proposals = sampled if sampled is not None else Proposals()
    for action in actions:
        proposals.add(action, list(enumerated.source.get(action, {})), "enumerate", enumerated.sampled.get(action, 0))
        proposals.add(action, prior.expressions(action), "prior", 0)  # without priors, nothing changes
    return proposals


def _known_rules(spec: Spec, prompted: Sequence[str], ranked: Mapping[str, Ranked]) -> dict[str, list[str]]:
    """The rules the evidence chose for the actions of the prompted ones' classes, to show the model."""
    classes = {spec.methods[a].cls for a in prompted}
    return {a: [c.representative.expression for c in r.chosen] for a, r in ranked.items()
            if r.chosen and spec.methods[a].cls in classes}


def _merged(first: EvaluateResult | None, rest: EvaluateResult) -> EvaluateResult:
    """The settled actions' judgments (made before the model was asked) beside the rest's: none judged twice."""
    if first is None:
        return rest
    return EvaluateResult({**rest.points, **first.points}, {**rest.results, **first.results})


def _without(request: InferRequest, traced: Traced) -> InferRequest:
    """The request with the left-out demonstrations empty and without the labelled calls of their runs."""
    runs = [r for r in request.counterexamples if r.demonstration not in traced.left_out]
    return request.model_copy(update={"demonstrations": traced.demonstrations, "counterexamples": runs})


def _separable(ranked: Ranked, policy: set[str] | None) -> list[str]:
    """The judged conditions the labelled calls are separated by (`counterexamples.separate`): every one, or for a
    tool spec the ranking's kept rules and the conditions over results and arguments (`policy`), the only ones
    its separation reads; the rest need not be judged again at the labelled calls."""
    kept = {c.representative.expression for c in ranked.chosen}
    return list(dict.fromkeys(r.expression for r in ranked.results if r.status != "rejected" and (
        not policy or r.expression in policy or r.expression in kept)))


def _timed_out(evaluated: EvaluateResult) -> dict[str, int]:
    """Per action, the candidates the sandbox dropped for running out of time: each is left out and counted, the
    request goes on."""
    counts = {a: sum((r.reason or "").startswith(TIMED_OUT) for r in results) for a, results in
              evaluated.results.items()}
    return {a: n for a, n in counts.items() if n}


def _judged_at(spec: Spec, actions: Sequence[str], trace: TraceResult) -> dict[str, list[Point]]:
    """A tool-calling agent's actions judged where a condition decides something (`engine.decisive`), those whose
    default grid is larger; every other action keeps the default grid."""
    cls = tool_class(spec)
    methods = [q for q, m in spec.methods.items() if m.cls == cls]
    found = {a: decisive_points(trace, trace.actions[a], methods) for a in actions
             if cls is not None and spec.methods[a].cls == cls}
    return {a: points for a, points in found.items() if points is not None}


def _refuse_no_evidence(actions: Sequence[str], trace: TraceResult) -> None:
    """No demonstration calls any of the actions: nothing to learn from (422); some: `notices` warns of each."""
    if not any(trace.actions[a].occurrences for a in actions):
        raise as_error(checks.no_occurrence_problem(list(actions), trace_count(trace)))


def trace_count(trace: TraceResult) -> int:
    return len(trace.positions)


def _same_place(a: ProgramError | None, b: ProgramError) -> bool:
    return a is not None and (a.where, a.index, a.line) == (b.where, b.index, b.line)


def _action_at(spec: Spec, demo: str, line: int, preconditions: dict[str, list[str]]) -> str | None:
    """The action with kept assertions called on a demonstration line (the one whose assertion failed)."""
    lines = demo.splitlines()
    text = lines[line - 1] if 0 < line <= len(lines) else ""
    for action, assertions in preconditions.items():
        if assertions and f".{spec.methods[action].name}(" in text:
            return action
    return None


def _question(action: str, ranked: Ranked, trace: TraceResult, n_points: int,
              options: InferOptions) -> judge.Question | None:
    """What the evidence left open for `action`, if anything: a rule for an action never or too thinly
    demonstrated (zero-shot), or a condition that held but looked like a phase."""
    occurrences = trace.actions[action].occurrences
    if not occurrences or thin(occurrences, options.tolerance):
        # With parameters and no occurrence there are no points at all: every valid candidate is an option.
        clusters = informative(cluster(ranked.valid), n_points)
        vacuous = [c.representative.expression for c in clusters] or [c.expression for c in ranked.valid]
        return judge.question(action, "zero-shot", vacuous, []) if vacuous else None
    if options.ranking != "recency":
        return None
    everything = [c.representative.expression for c in ranked.clusters]
    open_ = [c.representative.expression for c in ranked.clusters
             if c not in ranked.chosen and not any(k.satisfied & ~c.satisfied == 0 for k in ranked.chosen)]
    return judge.question(action, "phase", open_, everything) if open_ else None


def _exceptions_of(chosen: Mapping[str, Sequence[str]], ranked: Mapping[str, Ranked]) -> dict[int, set[int]]:
    """Demonstration -> positions of the calls that kept rules refuse by design (tolerated exceptions)."""
    steps: dict[int, set[int]] = {}
    for action, kept in chosen.items():
        for expression in kept:
            if ranked[action].verdicts.get(expression) == "tolerated":
                for occ in ranked[action].evidence[expression].exceptions:
                    steps.setdefault(occ.demo, set()).add(occ.position)
    return steps



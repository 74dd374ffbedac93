"""The paper's two procedures, in-process: precondition inference and verified next-action sampling.

Everything untrusted (spec, demonstrations, model output) is executed only through the sandbox; this module
decides what to run and how to read the answers. The model is loaded lazily, so model-free requests
(`enumerate`, `check`) never pay for it.
"""

from __future__ import annotations

import ast
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from precond.engine import scope
from precond.engine.acting.next_action import NextActionPlanner
from precond.engine.candidates import prompting
from precond.engine.candidates.enumeration import StateModel, enumerate_atoms
from precond.engine.candidates.library import Library, shipped
from precond.engine.candidates.parsing import parse_samples
from precond.engine.candidates.tool_conditions import separating, tool_atoms
from precond.engine.candidates.tool_relations import relations
from precond.engine.checking import Checking
from precond.engine.inference import (
    Run,
    Timer,
    action_at,
    chosen_rules,
    exempt_points,
    guarded_actions,
    judged_at,
    known_rules,
    merged,
    prompted_actions,
    proposals_of,
    question,
    refuse_no_evidence,
    same_place,
    separable,
    with_separations,
    without_left_out,
)
from precond.engine.judging import counterexamples, judge, priors
from precond.engine.judging.call_facts import about_the_call
from precond.engine.judging.dated_limits import with_dated_limits
from precond.engine.judging.evidence import OccurrenceIndex
from precond.engine.judging.freshness import writes_at
from precond.engine.judging.inference_notes import Findings, inference_warnings
from precond.engine.judging.ranking import (
    Cluster,
)
from precond.engine.judging.report import Proposals, Ranked, listed, report_of
from precond.engine.judging.runnable import drop_unrunnable
from precond.engine.judging.selection import Inference, select_rules
from precond.engine.judging.shared_rules import shared
from precond.engine.judging.unseen_shared import Calls, assume_shared
from precond.engine.left_out import trace_judgeable
from precond.engine.sandboxed import history_program, sandbox_call, spec_of
from precond.engine.spec import (
    Spec,
    check_preconditions,
    parse_source,
    parse_spec,
    render_program,
    resolve_actions,
    skip_statements,
)
from precond.engine.work import WorkBudget, points_of
from precond.sandbox.types import (
    EvaluateResult,
    Point,
    ProgramError,
    TraceResult,
)
from precond_client.schemas import (
    Decided,
    InferOptions,
    InferRequest,
    InferResponse,
    ModelInfo,
    NextActionRequest,
    NextActionResponse,
)
from precond_client.schemas.errors import (
    Cancelled,
    InvalidInput,
    InvalidProgram,
    ModelUnavailable,
)

if TYPE_CHECKING:
    from precond.engine.models import CodeModel
    from precond.engine.models.weights import Weights
    from precond.sandbox import Sandbox

ProgressFn = Callable[[str, int, int], None]
ModelLoader = Callable[[], "CodeModel"]
WeightsLoader = Callable[[], "Weights"]

MODEL_WAIT_POLL_S = 0.1
"""How often a job waiting for the model's load checks whether it was cancelled."""


def _no_progress(phase: str, done: int, total: int) -> None:
    return None


def _never() -> bool:
    return False


class Engine(Checking):
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
        """The inference as its stages: read and trace the request, enumerate, let the model propose, validate
        every candidate in the sandbox, rank (and judge, and separate the labelled calls), choose, verify the
        chosen rules together, then report with the warnings every stage left."""
        timer = Timer()
        progress("trace", 0, 1)
        run = self._read(request, timer)
        enumerated, stopped, policy = self._enumerated(run, timer)
        writes = writes_at(run.spec, run.trace) if request.options.ranking == "cautious" else {}
        first, proposals, model_info = self._proposed(run, enumerated, writes, timer, progress, cancelled)
        self._check_cancel(cancelled)
        progress("validate", 0, 1)
        evaluated, unrunnable = self._validated(run, first, proposals, timer)
        progress("rank", 0, 1)
        ranked, separated = self._ranked(run, evaluated, proposals, writes, policy, timer)
        chosen = chosen_rules(run, ranked, separated)
        ranked = dict(ranked)
        assume_shared(chosen, ranked, separated, run.guarded, run.spec.methods,
                      Calls(evaluated.points, {a: info.occurrences for a, info in run.trace.actions.items()}))
        with timer.phase("verify"):
            program, preconditions, dropped = self._verified_program(run.spec, chosen, run.demos,
                                                                     exempt_points(chosen, ranked, separated))
        response = report_of(run.actions, proposals, ranked, preconditions, dropped, timer.seconds, run.trace)
        with_separations(response.evidence, separated)
        findings = Findings(run.actions, run.trace, preconditions, ranked, run.request.options, model_info is not None,
                            run.prior.dropped, unrunnable, evaluated, separated, run.guarded, stopped,
                            run.traced.left_out)
        progress("done", 1, 1)
        return InferResponse(
            preconditions=preconditions, program=program, stats=response.stats,
            candidates=listed(response.candidates, request.options.candidates),
            model=model_info, warnings=inference_warnings(findings), evidence=response.evidence,
        )

    def _read(self, request: InferRequest, timer: Timer) -> Run:
        """The request read (spec, actions, demonstrations, labelled calls, priors, guarded actions: each refused
        naming its field before anything runs) and traced; a demonstration too large to judge is left out from
        here on (and named in the warnings)."""
        spec = parse_spec(request.spec)
        actions = resolve_actions(spec, request.actions)
        demos = list(request.demonstrations)
        trees = [parse_source(d, f"demonstrations[{i}]") for i, d in enumerate(demos)]
        labelled = counterexamples.read(spec, request.counterexamples, demos, actions) \
            if request.counterexamples else None
        prior = priors.collect(request.options, spec, actions, demos, self.library)
        guarded = guarded_actions(spec, actions, request.options)
        with timer.phase("trace"):
            traced = sandbox_call(trace_judgeable, self._sandbox, spec.source, demos, scope.current())
        if traced.left_out:  # too large to judge: each is empty from here on
            request, demos = without_left_out(request, traced), traced.demonstrations
            trees = [parse_source(d, f"demonstrations[{i}]") for i, d in enumerate(demos)]
            labelled = counterexamples.read(spec, request.counterexamples, demos, actions) \
                if request.counterexamples else None
        refuse_no_evidence(actions, traced.trace)
        return Run(request, spec, actions, demos, trees, labelled, prior, guarded, traced,
                    judged_at(spec, actions, traced.trace))

    def _enumerated(self, run: Run, timer: Timer) -> tuple[Proposals, dict[str, str], dict[str, set[str]]]:
        """The model-free candidates (when the request enumerates), where a search stopped, and a tool spec's
        conditions over results and arguments."""
        enumerated = Proposals()
        stopped: dict[str, str] = {}
        policy: dict[str, set[str]] = {}
        if "enumerate" in run.request.options.generators:
            with timer.phase("enumerate"):
                labelled_trees = [parse_source(p, "counterexamples") for p in run.labelled.programs] \
                    if run.labelled else []
                stopped = self._enumerate(run.spec, run.actions, run.demo_trees + labelled_trees, run.trace,
                                          enumerated, run.request.options.now, policy, run.judged_at,
                                          len(run.demo_trees))
        return enumerated, stopped, policy

    def _proposed(self, run: Run, enumerated: Proposals, writes: Any, timer: Timer, progress: ProgressFn,
                  cancelled: Callable[[], bool]) -> tuple[EvaluateResult | None, Proposals, ModelInfo | None]:
        """Every candidate: the code model's for the actions it is asked about (it reads the rules the evidence
        settles first, validated here), the enumerated ones and the priors."""
        options = run.request.options
        prompted = prompted_actions(run.actions, run.trace, options)
        settled = [a for a in run.actions if a not in prompted]
        proposals, model_info, first = Proposals(), None, None
        if "model" in options.generators and prompted:
            known: dict[str, list[str]] = {}
            if settled and options.show_rules:  # the evidence decides these first; the model reads them
                found = proposals_of(settled, enumerated, run.prior)
                with timer.phase("validate"):
                    first = self._evaluate(run, settled, found)
                with timer.phase("rank"):
                    known = known_rules(run.spec, prompted, select_rules(
                        settled, Inference(run.trace, first, found, options, writes, run.prior), run.guarded))
                self._check_cancel(cancelled)
            with timer.phase("generate"):
                model_info = self._generate(run.spec, run.actions, prompted, run.request, proposals, progress,
                                            cancelled, known)
        return first, proposals_of(run.actions, enumerated, run.prior, proposals), model_info

    def _evaluate(self, run: Run, actions: Sequence[str], proposals: Proposals) -> EvaluateResult:
        """The sandbox's verdicts on the candidates of `actions`, at each one's judged points."""
        return sandbox_call(self._sandbox.evaluate, run.spec.source, run.demos,
                            {a: list(proposals.source.get(a, {})) for a in actions},
                            {a: run.judged_at[a] for a in actions if a in run.judged_at}, scope=scope.current())

    def _validated(self, run: Run, first: EvaluateResult | None, proposals: Proposals, timer: Timer
                   ) -> tuple[EvaluateResult, dict[str, dict[str, str]]]:
        """Every candidate not validated yet, validated; those of never-demonstrated actions that cannot run on
        the spec's state dropped (and said why)."""
        with timer.phase("validate"):
            rest = [a for a in run.actions if first is None or a not in first.results]
            evaluated = merged(first, self._evaluate(run, rest, proposals))
        unseen = {a: not run.trace.actions[a].occurrences for a in run.actions}
        if not any(unseen.values()):
            return evaluated, {}
        return drop_unrunnable(run.spec, StateModel(run.spec, run.demo_trees), run.actions, evaluated, unseen)

    def _ranked(self, run: Run, evaluated: EvaluateResult, proposals: Proposals, writes: Any,
                policy: dict[str, set[str]], timer: Timer
                ) -> tuple[dict[str, Ranked], dict[str, counterexamples.Separation]]:
        """Each action's rules by the ranking criterion, then the code model's judgment where asked, then the
        labelled calls' separation."""
        options = run.request.options
        with timer.phase("rank"):
            ranked = select_rules(run.actions, Inference(run.trace, evaluated, proposals, options, writes, run.prior),
                                  run.guarded)
            ranked = {a: about_the_call(with_dated_limits(r, policy[a]), run.spec.methods[a].positional)
                      if a in policy else r for a, r in ranked.items()}
        if options.judge:
            with timer.phase("judge"):
                ranked = self._judge(run.spec, run.actions, run.demos, run.trace, evaluated, ranked, options)
        separated: dict[str, counterexamples.Separation] = {}
        if run.labelled is not None:
            with timer.phase("counterexamples"):
                separated = self._separate(run.spec, run.labelled, run.trace, evaluated, ranked, policy, run.demos)
            ranked = {**ranked, **{a: s.ranked for a, s in separated.items()}}
        return ranked, separated

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
        asked = {a: [p for _, p in where[a]] for a in sorted(labelled.actions()) if where.get(a)}
        judged = sandbox_call(self._sandbox.evaluate, spec.source, labelled.programs,
                              {a: separable(ranked[a], policy.get(a)) for a in asked}, asked,
                              scope=scope.current()) if asked else None  # every action's in one run of the runs
        separated = {}
        for action in sorted(labelled.actions()):
            cases = where.get(action, [])
            results: dict[str, Any] = {}
            order: list[Any] = [p for _, p in cases]
            if cases and judged is not None:
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
                     and (q := question(a, ranked[a], trace, len(evaluated.points.get(a, ())), options)) is not None]
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
            action = action_at(spec, demos[failure.index or 0], failure.line or 0, preconditions)
            if failure.where != "demonstration" or action is None:
                raise InvalidProgram(str(failure), field=f"demonstrations[{failure.index}]")
            kept = preconditions[action]
            culprit = next(
                (i for i in reversed(range(len(kept)))
                 if not same_place(self._failure(spec, {**preconditions, action: kept[:i] + kept[i + 1:]}, demos),
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
        spec = parse_spec(spec_of(request))
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


    @staticmethod
    def _check_cancel(cancelled: Callable[[], bool]) -> None:
        if cancelled():
            raise Cancelled("job cancelled")



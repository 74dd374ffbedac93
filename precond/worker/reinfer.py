"""Re-inference of a stored precondition set (job kind `reinfer`): the engine's inference on the set's spec with
its stored demonstrations and the new ones, merged with the base version (`store.reinference.merge`: required rules
kept, rejected ones kept out), judged against all demonstrations, and stored as the next version.

The computing (`reinfer`) runs in the engine's thread; the storing (`keep`, over `store.reinference.store`) on the
event loop, after it.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from precond.engine.engine import Engine
from precond.engine.judging import counterexamples
from precond.engine.spec import parse_spec, resolve_actions
from precond.jobs.queue.keys import JobId
from precond.jobs.queue.payloads import Outcome, ReinferJob
from precond.store import reinference, sets
from precond_client.schemas import Counterexamples, InferRequest, PreconditionSet, ValidateResponse
from precond_client.schemas.errors import BlocksDemonstration, InvalidInput, PrecondError

ProgressFn = Callable[[str, int, int], None]
CancelledFn = Callable[[], bool]
_DEMO_FIELD = re.compile(r"^demonstrations\[(\d+)\]")


def _fields(job: ReinferJob, demos: list[str]) -> Callable[[str | None], str | None]:
    """Field of the union of demonstrations → field of the request: a new demonstration is named by its index
    in the request (`demonstrations[i]`), a stored one as `base.demonstrations[i]`."""
    stored = len(job.base.demonstrations)

    def field(name: str | None) -> str | None:
        match = _DEMO_FIELD.match(name or "")
        if match is None:
            return name
        index = int(match.group(1))
        if index < stored:
            return f"base.demonstrations[{index}]" + name[match.end():]  # type: ignore[index]
        return f"demonstrations[{job.demonstrations.index(demos[index])}]" + name[match.end():]  # type: ignore[index]

    return field


def reinfer(engine: Engine, job: ReinferJob, progress: ProgressFn, cancelled: CancelledFn) -> PreconditionSet:
    base = job.base
    demos = sets.union(base.demonstrations, job.demonstrations)
    field = _fields(job, demos)
    labelled: list[Counterexamples] = []
    try:
        _check_required(engine, job, demos, field, progress)
        options = job.options.model_copy(update={"candidates": "all"})  # the diff's reasons come from them
        spec = parse_spec(base.spec)
        labelled = counterexamples.of_actions(spec, [*base.counterexamples, *job.counterexamples], demos,
                                              resolve_actions(spec, job.actions))
        request = InferRequest(spec=base.spec, demonstrations=demos, actions=job.actions, options=options,
                               counterexamples=labelled)
        inferred = engine.infer(request, progress, cancelled)
        merged = reinference.merge(base, inferred.preconditions, inferred.candidates,
                                   len(demos) - len(base.demonstrations), job.actions)
        problem = sets.over_bounds(merged.preconditions)
        if problem is not None:
            raise InvalidInput(f"the re-inferred version: {problem} (its required rules and the inferred ones); "
                               "un-require or reject some of them first", field="actions")
        judged = {a: list(dict.fromkeys([*merged.preconditions.get(a, []), *merged.unexplained.get(a, [])]))
                  for a in {*merged.preconditions, *merged.unexplained}}
        progress("validate", 0, 1)
        report = (engine.validate(base.spec, judged, demos)
                  if judged else ValidateResponse())
    except PrecondError as exc:
        exc.field = field(_counterexample_field(exc.field, base.counterexamples, job.counterexamples, labelled))
        raise
    blocked: dict[tuple[str, str], str] = {}
    for b in report.blocked:
        blocked.setdefault((b.action, b.rule), f"{field(f'demonstrations[{b.demonstration}]')}, line {b.line} "
                                               f"({b.call})")
    final = {(a, r) for a, rs in merged.preconditions.items() for r in rs}
    validation = ValidateResponse(
        blocked=[b for b in report.blocked if (b.action, b.rule) in final],
        unjudged={k: v for k, v in report.unjudged.items() if tuple(k.split(": ", 1)) in final},
    )
    number = base.latest + 1
    evidence = {**base.evidence, **inferred.evidence}  # actions not re-inferred keep what was said of them
    candidates = {**base.candidates, **inferred.candidates}
    return PreconditionSet(
        id=base.id, version=number, latest=number, reference=f"{base.id}@{number}",
        created=datetime.now(UTC).isoformat(timespec="seconds"), spec=base.spec,
        preconditions=merged.preconditions, demonstrations=demos, required=base.required, rejected=base.rejected,
        counterexamples=[*base.counterexamples, *job.counterexamples],
        edits=[], validation=validation,
        diff=reinference.explain_removed(merged, blocked),
        warnings=_warnings(job, merged.preconditions, inferred.warnings), evidence=evidence,
        candidates=candidates, decided=sets.decided(merged.preconditions, evidence, candidates),
    )


def _check_required(engine: Engine, job: ReinferJob, demos: list[str], field: Callable[[str | None], str | None],
                    progress: ProgressFn) -> None:
    """Refuse (BlocksDemonstration) when a rule the reviewer required would block a new demonstration, unless the
    request forces the re-inference: the new demonstrations would otherwise contradict the set they extend."""
    base = job.base
    required = {action: rules for action, rules in base.required.items() if rules}
    if not required:
        return
    progress("validate required", 0, 1)
    report = engine.validate(base.spec, required, demos)
    new = [b for b in report.blocked if b.demonstration >= len(base.demonstrations)]
    if new and not job.force:
        first = new[0]
        where = f"demonstrations[{first.demonstration}]"  # of the union: renamed by the caller, like any field
        more = f", and {len(new) - 1} more demonstrated call(s)" if len(new) > 1 else ""
        raise BlocksDemonstration(
            f"required rule {first.rule!r} of {first.action} would block {field(where)}, line {first.line} "
            f"({first.call}){more}; fix the demonstration, un-require the rule, or send force: true",
            field=where,
        )


_LABEL_FIELD = re.compile(r"^counterexamples\[(\d+)\]")


def _counterexample_field(name: str | None, stored: list[Counterexamples], new: list[Counterexamples],
                          sent: list[Counterexamples]) -> str | None:
    """Field of the inference's counterexamples → the set's (`base.counterexamples[i]`) or this request's (the
    new call: `call`)."""
    match = _LABEL_FIELD.match(name or "")
    if match is None or name is None:
        return name
    run = sent[int(match.group(1))]
    if any(run is mine for mine in new):
        return "call"
    return f"base.counterexamples[{next(i for i, r in enumerate(stored) if r is run)}]" + name[match.end():]


def _warnings(job: ReinferJob, rules: dict[str, list[str]], inferred: dict[str, str]) -> dict[str, str]:
    """The inference's warnings, the base's for the actions not re-inferred, and every empty rule's."""
    base = job.base
    kept = {a: w for a, w in base.warnings.items() if job.actions is not None and a not in job.actions}
    return sets.set_warnings(base.spec, rules, base.rejected, {**kept, **inferred})


async def keep(redis: Any, job: JobId, body: dict[str, Any], result: dict[str, Any]) -> Outcome:
    """A re-inference's version, stored (the set's next version) or refused (conflict, bounds): its outcome."""
    try:
        stored = await reinference.store(redis, job.tenant, ReinferJob.model_validate(body),
                                         PreconditionSet.model_validate(result))
    except PrecondError as exc:
        return Outcome.failed(exc)
    return Outcome(status="succeeded", result=stored.model_dump(mode="json"))

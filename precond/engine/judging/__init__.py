"""Judging candidate rules on the demonstrations: evidence and decisive points, labelled counterexamples,
runnability, ranking (the cautious criterion by default), freshness, guarded actions, the code model
as judge, priors, each action's selection, the inference's report and warnings.

Its public names are importable from here, each loaded from its module on first use (`engine.faces`)."""

from __future__ import annotations

from precond.engine.faces import lazy

_SOURCES: dict[str, tuple[str, ...]] = {
    "precond.engine.judging.call_facts": ("about_the_call",),
    "precond.engine.judging.dated_limits": ("with_dated_limits",),
    "precond.engine.judging.decisive": ("decisive_points",),
    "precond.engine.judging.evidence": ("OccurrenceIndex", "thin", "too_few"),
    "precond.engine.judging.freshness": ("writes_at",),
    "precond.engine.judging.inference_notes": ("Findings", "inference_warnings"),
    "precond.engine.judging.ranking": ("ActionEvidence", "Candidate", "Cluster", "cluster", "informative", "rank"),
    "precond.engine.judging.report": ("Proposals", "Ranked", "UNSEEN_RULE", "listed", "report_of"),
    "precond.engine.judging.runnable": ("drop_unrunnable",),
    "precond.engine.judging.selection": ("Inference", "previous_turns", "select_rules"),
    "precond.engine.judging.shared_rules": ("shared",),
    "precond.engine.judging.unseen_shared": ("Calls", "assume_shared"),
}
__all__ = sorted(name for names in _SOURCES.values() for name in names)
__getattr__ = lazy(__name__, _SOURCES)

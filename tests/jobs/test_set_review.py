"""How a stored rule was decided (`store.sets.how_decided`): the engine's word when it gives one,
otherwise read from the evidence and the candidate's reason; and the summary the list of sets shows."""

from __future__ import annotations

import json
from types import SimpleNamespace
from typing import Any

import pytest

from precond.store.sets import decided, how_decided, summary
from precond_client.schemas import CandidateReport, PreconditionSet, RuleEvidence


def _evidence(occurrences: int, verdict: str = "held") -> RuleEvidence:
    return RuleEvidence(occurrences=occurrences, holds=occurrences, confidence=0.5, verdict=verdict)  # type: ignore[arg-type]


def _report(reason: str) -> CandidateReport:
    return CandidateReport(assertion="self.a", source="enumerate", valid=True, support=1, kept=True, reason=reason)


@pytest.mark.parametrize(("evidence", "reason", "label"), [
    (_evidence(12), "kept: held at every occurrence", "established"),
    (_evidence(2), "kept: held at every occurrence", "assumed"),  # seen twice: a human should read it
    (_evidence(5, "thin"), "kept", "assumed"),
    (_evidence(0), "zero-shot: never demonstrated, kept by model vote (3 samples proposed it, the most)", "zero-shot"),
    (_evidence(9), "kept by the code model's judgment (held, but looked like a phase): log-likelihood -2.1", "assumed"),
    (_evidence(0), "kept by the code model's judgment (never demonstrated, so the evidence cannot choose)",
     "zero-shot"),
    (None, None, "no evidence"),
])
def test_a_label_is_read_from_what_the_inference_said(evidence: RuleEvidence | None, reason: str | None,
                                                      label: str) -> None:
    assert how_decided(evidence, None if reason is None else _report(reason)) == label


def test_the_engines_own_word_wins() -> None:
    stated: Any = SimpleNamespace(decided="transferred", occurrences=0, verdict="thin")
    assert how_decided(stated, None) == "transferred"


def test_every_rule_of_a_version_is_labelled_and_counted() -> None:
    rules = {"SYSTEM.INFORM": ["self.a", "self.b  and self.c"], "SYSTEM.BYE": ["self.done"]}
    evidence = {"SYSTEM.INFORM": {"self.a": _evidence(1), "self.b and self.c": _evidence(30)}}
    labels = decided(rules, evidence, {})
    assert labels == {"SYSTEM.INFORM": {"self.a": "assumed", "self.b  and self.c": "established"},
                      "SYSTEM.BYE": {"self.done": "no evidence"}}
    version = PreconditionSet(id="ps_1", version=2, latest=2, reference="ps_1@2", created="2026-01-01T00:00:00+00:00",
                              spec="", preconditions=rules, decided=labels, rejected={"SYSTEM.BYE": ["self.x"]},
                              warnings={"SYSTEM.NOTIFY": "no occurrence"})
    line = json.loads(summary(version))
    assert (line["rules"], line["assumed"], line["zero_shot"], line["no_evidence"], line["rejected"]) == (3, 1, 0, 1, 1)
    assert line["actions"] == ["SYSTEM.BYE", "SYSTEM.INFORM", "SYSTEM.NOTIFY"] and line["reference"] == "ps_1@2"

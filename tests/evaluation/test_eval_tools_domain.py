"""`precond eval tools --domain`: a tool-calling domain written from scratch, converted, inferred (model-free,
every tool guarded) and scored on its own test set, whose verdicts were written from its policy before any rule
was learned (tests/fixtures/tools_domains/). Runs through the real engine and sandbox; the numbers it prints are
what the learner achieves there, asserted only where any correct scoring must agree."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from precond.engine.factory import build_engine
from precond.evaluation import tools_domain
from tests.cli.inprocess import precond

pytestmark = pytest.mark.long  # collected first: pytest-xdist starts it first

DOMAINS = Path(__file__).resolve().parents[1] / "fixtures" / "tools_domains"


@pytest.mark.parametrize("name", ["clinic", "cards", "rental"])
def test_a_domain_from_scratch_is_converted_inferred_and_scored(name: str) -> None:
    result = tools_domain.run(build_engine(with_model=False), DOMAINS / name, print)
    print(tools_domain.table(result))
    verdicts = json.loads((DOMAINS / name / "test_verdicts.json").read_text())
    bad = sum(not v["allowed"] for v in verdicts)
    tools = {t["function"]["name"] for t in json.loads((DOMAINS / name / "tools.json").read_text())}
    assert result["guarded"] == sorted(tools)  # the reads are guarded too
    for mode in ("without labels", "with labels"):
        total = result[mode]["total"]
        assert (total["calls"], total["labelled_refused"], total["labelled_allowed"]) == (
            len(verdicts), bad, len(verdicts) - bad)
        assert 0 <= total["unsafe_allowed"] <= bad and 0 <= total["over_refused"] <= len(verdicts) - bad
        assert set(result[mode]["rules"]) == {f"AGENT.{t}" for t in tools}
        by_rule = result[mode]["per_rule"]
        assert sum(s["labelled_refused"] for s in by_rule.values()) == bad
        assert len(result[mode]["misjudged"]) == total["unsafe_allowed"] + total["over_refused"]
    held = result["labels left out one run at a time"]
    assert held["labelled_refused"] == result["labels"] == 7


def test_the_command_scores_a_domain_and_a_missing_test_set_exits_2(tmp_path: Path) -> None:
    (tmp_path / "tools.json").write_text((DOMAINS / "cards" / "tools.json").read_text())
    (tmp_path / "trajectories.json").write_text((DOMAINS / "cards" / "trajectories.json").read_text())
    done = precond("eval", "tools", "--domain", str(tmp_path), "--cache", str(tmp_path / "cache"))
    assert done.returncode == 2 and "test.json: no such file" in done.stderr, done.stderr


def test_without_labels_the_learner_reads_the_good_runs_alone() -> None:
    # a run that ends in a labelled bad call is no demonstration, whether its label is given or left out
    train, labels, _, _ = tools_domain.load(DOMAINS / "cards")
    refused = {label.run for label in labels if not label.allowed}
    good = [t.program for t in train.trajectories if t.name not in refused]
    for taught in ([], labels[1:], labels):
        request = tools_domain.infer_request(train, labels, taught)
        assert request.demonstrations == good
        assert len(request.counterexamples) == len({label.run for label in taught})

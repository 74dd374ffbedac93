"""The learner's data-driven choices: F1 decides only among candidates that raise the counterfactual unsafe share on
no development domain beyond noise; each held-out domain's pick is made without it; the command fails a shipped
default that is not the pick, and `eval domains --unsafe-against` fails a config less safe than the reference."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from precond.cli import eval_commands
from precond.cli.main import app
from precond.engine.candidates.library import SIGNED
from precond.evaluation.choice import CHOICES, Choice, by_candidate, decide, noise, pick, raised_against, raises
from precond.evaluation.configs import NOTICE_READINGS, parse_config
from precond.evaluation.library import source_config


def _row(config: str, domain: str, f1: float, unsafe: int, refusals: int = 400) -> dict[str, Any]:
    """One domain with one action whose truth refuses `refusals` points, `unsafe` of them allowed."""
    return {"config": config, "domain": domain, "benchmark": "sgd", "f1": f1, "unsafe_allow": unsafe / refusals,
            "over_refuse": 0.1, "error": None, "variants": 4, "seed": 0,
            "actions": {"SYSTEM.A": {"unsafe": unsafe, "refusals": refusals}}}


CHOICE = Choice("toy", "a toy choice", {"safe": "", "loose": "x=1"}, "safe")


def _table(loose_unsafe_on_c: int) -> dict[str, dict[str, Any]]:
    rows = [_row("b", d, 0.90, 0) for d in "ABC"]
    rows += [_row("b/x=1", "A", 0.95, 0), _row("b/x=1", "B", 0.95, 1), _row("b/x=1", "C", 0.95, loose_unsafe_on_c)]
    return by_candidate(CHOICE, "b", rows)


def test_a_choice_that_raises_unsafe_on_one_domain_beyond_noise_is_not_taken_whatever_its_f1() -> None:
    table = _table(loose_unsafe_on_c=400)
    assert [r.domain for r in raises(table, "loose", ["A", "B", "C"])] == ["C"]
    assert pick(table, ["A", "B", "C"]) == "safe"


def test_a_rise_within_noise_does_not_stop_the_better_f1() -> None:
    table = _table(loose_unsafe_on_c=2)  # 2 of 400 against 0 of 400: within two standard errors
    assert raises(table, "loose", ["A", "B", "C"]) == []
    assert pick(table, ["A", "B", "C"]) == "loose"
    assert noise(table["loose"]["C"], table["safe"]["C"]) > 2 / 400


def test_each_held_out_domain_is_picked_for_without_its_own_scores() -> None:
    outcome = decide(CHOICE, _table(loose_unsafe_on_c=400))
    assert outcome.picked == "safe"
    assert outcome.held_out == {"A": "safe", "B": "safe", "C": "loose"}  # only C shows the rise
    assert "C 0.000 (safe) -> 1.000" in outcome.text and "shipped: `safe`." in outcome.text


def test_the_signed_notices_shipped_are_the_reading_the_procedure_ships() -> None:
    notices = next(c for c in CHOICES if c.name == "signed notices")
    assert NOTICE_READINGS[notices.shipped] == dict(SIGNED)
    config = parse_config(f"enumerate/cautious/guard=spec/lib=lodo/{notices.candidates['empty']}")
    assert config.notices == "empty" and source_config(config).name == "enumerate/cautious/guard=spec"
    with pytest.raises(ValueError, match="notices="):
        parse_config("enumerate/cautious/lib=lodo/notices=loose")


def _fake_runs(monkeypatch: pytest.MonkeyPatch, rows: list[dict[str, Any]]) -> None:
    from precond.evaluation import safety
    monkeypatch.setattr(safety, "evaluate", lambda *args, **kwargs: rows)
    monkeypatch.setattr(eval_commands, "_domains", lambda *args: [])
    monkeypatch.setattr(eval_commands, "_sandbox", lambda: None)
    monkeypatch.setattr(eval_commands, "_memo_engine", lambda store: (None,))


def test_the_choose_command_fails_naming_a_choice_whose_shipped_default_is_not_the_pick(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    slips = next(c for c in CHOICES if c.name == "answer slips")
    base = "enumerate/cautious/guard=spec/lib=lodo"
    rows = [_row(base, d, 0.90, 0) for d in "AB"] + [_row(f"{base}/slips=0", d, 0.95, 0) for d in "AB"]
    _fake_runs(monkeypatch, rows)
    result = CliRunner().invoke(app, ["eval", "choose", "--choices", slips.name, "--cache", str(tmp_path)])
    assert result.exit_code == 1 and "answer slips: picked 0, ships 0.3" in result.output
    rows[2]["f1"] = rows[3]["f1"] = 0.85
    assert CliRunner().invoke(app, ["eval", "choose", "--choices", slips.name, "--cache", str(tmp_path)]).exit_code == 0
    assert CliRunner().invoke(app, ["eval", "choose", "--choices", "nothing", "--cache", str(tmp_path)]).exit_code == 2


def test_the_domains_command_fails_a_config_less_safe_than_the_reference_naming_the_domain(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    rows = [_row("b", "A", 0.9, 0), _row("b", "B", 0.9, 0), _row("b/x=1", "A", 0.95, 1),
            _row("b/x=1", "B", 0.95, 300)]
    assert raised_against(rows, "b") == [
        "b/x=1 on sgd B: unsafe 0.750 against 0.000 (b), noise 0.044 (F1 0.950)"]
    _fake_runs(monkeypatch, rows)
    common = ["eval", "domains", "--configs", "always", "--cache", str(tmp_path / "c"), "--out",
              str(tmp_path / "r.md")]
    failed = CliRunner().invoke(app, [*common, "--unsafe-against", "enumerate/cautious"])
    assert failed.exit_code == 0  # no row of that reference: nothing to compare
    rows += [{**r, "config": "enumerate/cautious"} for r in rows[:2]]
    failed = CliRunner().invoke(app, [*common, "--unsafe-against", "enumerate/cautious"])
    assert failed.exit_code == 1 and "b/x=1 on sgd B: unsafe 0.750 against 0.000" in failed.output

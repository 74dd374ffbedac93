"""The twenty-domain summary: a mean cannot hide a domain (worst domain, domains at or below `always`), and each
row says how it was chosen; the leave-one-domain-out settings parse into requests."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from precond.cli import eval_commands
from precond.cli.main import app
from precond.evaluation.configs import parse_config
from precond.evaluation.generalisation import (
    HOW_CHOSEN,
    costly_actions,
    how_chosen,
    section,
    summarize,
    unsafe_breaches,
)
from precond.evaluation.library import source_config


def _row(config: str, domain: str, benchmark: str, f1: float, unsafe: float | None = 0.0,
         over: float | None = 0.0) -> dict[str, object]:
    return {"config": config, "domain": domain, "benchmark": benchmark, "f1": f1, "unsafe_allow": unsafe,
            "over_refuse": over, "variants": 4, "seed": 0, "error": None}


ROWS = [_row("always", "A", "sgd", 0.5, None, 0.0), _row("always", "B", "sgd", 0.6, None, 0.0),
        _row("always", "t", "star", 0.7, None, 0.0),
        _row("x/cautious", "A", "sgd", 0.95, 0.1, 0.2), _row("x/cautious", "B", "sgd", 0.55, 0.3, 0.1),
        _row("x/cautious", "t", "star", 0.9, None, 0.4)]


def _scored(over: int, allows: int, unsafe: int, refusals: int, rules: list[str]) -> dict[str, object]:
    return {"over": over, "allows": allows, "over_refuse": over / allows if allows else None, "unsafe": unsafe,
            "refusals": refusals, "unsafe_allow": unsafe / refusals if refusals else None, "rules": rules}


def _with_actions(row: dict[str, object], actions: dict[str, dict[str, object]]) -> dict[str, object]:
    return {**row, "actions": actions}


ACTED = [
    _with_actions(_row("x/cautious", "A", "sgd", 0.9), {
        "S.NOTIFY": _scored(6, 10, 0, 4, ["self.query_success is False"]),
        "S.GOODBYE": _scored(0, 10, 0, 0, [])}),
    _with_actions(_row("x/cautious", "B", "sgd", 0.9), {
        "S.REQUEST": _scored(1, 10, 3, 4, ["not self.user.informed_slot[slot]"]),
        "S.Book": _scored(2, 10, 1, 10, ["self.user.affirmed"])}),
    _with_actions(_row("x/cautious", "t", "star", 0.9), {"S.NOTIFY": _scored(0, 10, 0, 10, ["False"])}),
    _with_actions(_row("always", "A", "sgd", 0.5), {"S.NOTIFY": _scored(0, 10, 4, 4, [])}),
]


def test_the_costliest_actions_of_a_config_are_named_per_benchmark_with_their_counts_and_rules() -> None:
    text = costly_actions(ACTED, "x/cautious", 1)
    assert "| sgd | over | A | S.NOTIFY | 0.600 (6/10) | `self.query_success is False` |" in text
    assert "| sgd | unsafe | B | S.REQUEST | 0.750 (3/4) | `not self.user.informed_slot[slot]` |" in text
    assert "S.Book" not in text and "S.GOODBYE" not in text  # beyond the first one of each
    assert "| star | over" not in text and "| star | unsafe" not in text  # nothing over-refused or let through
    assert "| sgd | unsafe | A | S.NOTIFY" not in text  # another config's actions
    assert "S.Book" in costly_actions(ACTED, "x/cautious", 2) and costly_actions(ACTED, "x/cautious", 0) == ""


def test_the_worst_domain_and_the_domains_at_or_below_always_are_counted_per_benchmark() -> None:
    found = {(s.config, s.benchmark): s for s in summarize(ROWS)}
    sgd = found[("x/cautious", "sgd")]
    assert sgd.f1_mean == pytest.approx(0.75) and sgd.f1_worst == ("B", 0.55)
    assert sgd.at_or_below_always == ["B"]
    assert sgd.unsafe_worst == ("B", 0.3) and sgd.over_worst == ("A", 0.2)
    star = found[("x/cautious", "star")]
    assert star.at_or_below_always == [] and star.unsafe_mean is None
    assert found[("always", "sgd")].at_or_below_always == ["A", "B"]


def test_an_errored_domain_is_not_averaged_as_a_score() -> None:
    rows = [*ROWS, {"config": "x/cautious", "domain": "C", "benchmark": "sgd", "error": "boom", "variants": 4,
                    "seed": 0}]
    assert {s.benchmark: s.domains for s in summarize(rows) if s.config == "x/cautious"} == {"sgd": 2, "star": 1}


def test_every_row_says_how_it_was_chosen() -> None:
    text = section(ROWS, {"x/cautious": "leave-one-domain-out: the test"})
    assert "leave-one-domain-out: the test" in text and HOW_CHOSEN["always"] in text
    assert "| sgd | `x/cautious` | 2 | 0.750 | 0.550 (B) | 1 (B) |" in text


def test_library_and_guard_settings_reach_the_request() -> None:
    lodo = parse_config("model+enumerate/cautious/guard=spec/lib=lodo")
    options = lodo.infer_options(["SYSTEM.GOODBYE", "SYSTEM.Book"])
    assert options.library and options.guarded is None
    plain = parse_config("enumerate/cautious").infer_options(["SYSTEM.GOODBYE", "SYSTEM.Book"])
    assert not plain.library and plain.guarded == ["SYSTEM.GOODBYE", "SYSTEM.Book"]
    assert source_config(lodo).name == "model+enumerate/cautious/guard=spec"
    with pytest.raises(ValueError, match="lib="):
        parse_config("enumerate/cautious/lib=1")


def test_answer_slips_reach_the_request_and_the_row_says_so() -> None:
    config = parse_config("enumerate/cautious/guard=spec/lib=lodo/slips=0")
    assert config.infer_options(["SYSTEM.Book"]).answer_slips == 0.0
    assert source_config(config).name == "enumerate/cautious/guard=spec/slips=0"
    assert "answer_slips" in how_chosen(config.name)


def test_a_config_above_the_unsafe_bound_on_any_domain_is_named_with_its_numbers() -> None:
    assert unsafe_breaches(ROWS, 0.3) == []
    assert unsafe_breaches(ROWS, 0.2) == ["x/cautious on sgd B: unsafe 0.300 > 0.200 (F1 0.550)"]
    assert len(unsafe_breaches([*ROWS, _row("always", "C", "sgd", 0.5, 1.0)], 0.05)) == 2  # baselines are no choice


def test_the_domains_command_fails_a_config_above_the_bound(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from precond.evaluation import safety
    rows = [*ROWS, _row("always", "A", "sgd", 0.5, 1.0)]
    monkeypatch.setattr(safety, "evaluate", lambda *args, **kwargs: rows)
    monkeypatch.setattr(eval_commands, "_domains", lambda *args: [])
    monkeypatch.setattr(eval_commands, "_sandbox", lambda: None)
    monkeypatch.setattr(eval_commands, "_memo_engine", lambda store: (None,))
    out = tmp_path / "results.md"
    common = ["eval", "domains", "--configs", "always", "--cache", str(tmp_path / "c"), "--out", str(out)]
    failed = CliRunner().invoke(app, [*common, "--max-unsafe", "0.2"])
    assert failed.exit_code == 1 and "x/cautious on sgd B: unsafe 0.300 > 0.200" in failed.output
    assert CliRunner().invoke(app, [*common, "--max-unsafe", "0.3"]).exit_code == 0
    assert CliRunner().invoke(app, [*common, "--max-unsafe", "-1"]).exit_code == 2


def test_the_domains_command_prints_the_costliest_actions_of_the_first_config_measured(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from precond.evaluation import safety
    monkeypatch.setattr(safety, "evaluate", lambda *args, **kwargs: ACTED)
    monkeypatch.setattr(eval_commands, "_domains", lambda *args: [])
    monkeypatch.setattr(eval_commands, "_sandbox", lambda: None)
    monkeypatch.setattr(eval_commands, "_memo_engine", lambda store: (None,))
    common = ["eval", "domains", "--configs", "always", "--cache", str(tmp_path / "c"), "--out",
              str(tmp_path / "results.md")]
    shown = CliRunner().invoke(app, [*common, "--actions", "1"])
    assert shown.exit_code == 0 and "| sgd | over | A | S.NOTIFY | 0.600 (6/10) |" in shown.output
    assert "| sgd | over |" not in CliRunner().invoke(app, common).output

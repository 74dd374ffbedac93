"""A domain directory that is missing or malformed stops an evaluation with its path (exit 2), before anything is
inferred or scored: a table of the domains that could be read is never presented as the whole."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from precond.cli.main import app
from precond.evaluation.domains import DomainDataError, load_domains

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "data"
GOOD = FIXTURES / "sgd" / "Events_1.json"


def _sgd_dir(tmp_path: Path, **broken: str) -> Path:
    """A copy of a fixture SGD service, plus the files named by `broken` (file name -> content)."""
    folder = tmp_path / "sgd"
    folder.mkdir()
    shutil.copy(GOOD, folder / GOOD.name)
    for name, text in broken.items():
        (folder / name).write_text(text, encoding="utf-8")
    return folder


def _without(field: str) -> str:
    data = json.loads(GOOD.read_text(encoding="utf-8"))
    del data[field]
    return json.dumps(data)


CASES = {
    "not JSON": ({"Zebra_1.json": '{"service": "Zebra_1", '}, "Zebra_1.json", "JSONDecodeError"),
    "a field missing": ({"Zebra_1.json": _without("spec_program")}, "Zebra_1.json", "missing field 'spec_program'"),
    "a list where an object belongs": ({"Zebra_1.json": "[]"}, "Zebra_1.json", "TypeError"),
}


@pytest.mark.parametrize("case", CASES)
def test_a_malformed_service_file_is_named_not_skipped(tmp_path: Path, case: str) -> None:
    files, named, problem = CASES[case]
    folder = _sgd_dir(tmp_path, **files)
    with pytest.raises(DomainDataError) as raised:
        load_domains(folder)
    assert str(folder / named) in str(raised.value) and problem in str(raised.value)


def test_a_missing_empty_or_file_directory_is_named(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "file.json").write_text("{}")
    for path, problem in [(tmp_path / "gone", "does not exist"), (tmp_path / "empty", "neither SGD domain files"),
                          (tmp_path / "file.json", "not a directory")]:
        with pytest.raises(DomainDataError, match=problem) as raised:
            load_domains(path)
        assert str(path) in str(raised.value)


def test_an_alfworld_directory_without_a_file_names_the_file(tmp_path: Path) -> None:
    folder = tmp_path / "alfworld"
    shutil.copytree(FIXTURES / "alfworld", folder)
    (folder / "test_admissible_commands.json").unlink(missing_ok=True)
    with pytest.raises(DomainDataError) as raised:
        load_domains(folder)
    assert "test_admissible_commands.json" in str(raised.value) and str(folder) in str(raised.value)


def test_a_well_formed_directory_still_loads(tmp_path: Path) -> None:
    assert [d.name for d in load_domains(_sgd_dir(tmp_path))] == ["Events_1"]


@pytest.mark.parametrize("command", ["preconditions", "counterfactual"])
def test_the_cli_exits_2_naming_the_file_and_prints_no_table(tmp_path: Path, command: str) -> None:
    folder = _sgd_dir(tmp_path, **{"Zebra_1.json": "[]"})
    result = CliRunner().invoke(app, ["eval", command, "--data", str(folder), "--configs", "always",
                                      "--cache", str(tmp_path / "cache")])
    assert result.exit_code == 2, result.output
    assert f"error: malformed domain data {folder / 'Zebra_1.json'}" in result.output
    assert "|" not in result.output and not (tmp_path / "cache").exists()  # nothing scored, nothing stored


def test_a_mean_over_the_domains_that_ran_is_marked_incomplete() -> None:
    """A domain whose inference failed (a domain file the engine refuses) is `error` in its cell, and the SGD
    mean over the others says it is incomplete instead of reading as the benchmark's."""
    from precond.evaluation.safety import table

    ran = {"f1": 0.9, "unsafe_allow": 0.1, "over_refuse": 0.05, "error": None}
    rows = [{"config": "c", "domain": "A_1", "benchmark": "sgd", **ran},
            {"config": "c", "domain": "B_1", "benchmark": "sgd", "error": "invalid_input: demonstrations: none"},
            {"config": "d", "domain": "A_1", "benchmark": "sgd", **ran},
            {"config": "d", "domain": "B_1", "benchmark": "sgd", **ran}]
    lines = table(rows).splitlines()
    assert lines[2] == "| `c` | 0.900 / 0.100 / 0.050 | error | incomplete: 1 of 2 domains failed |"
    assert lines[3].endswith("| 0.900 / 0.100 / 0.050 |")


def test_a_run_that_lost_a_domain_exits_1_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    import typer

    from precond.cli.eval_commands import _fail_on_errors

    _fail_on_errors([{"config": "c", "domain": "A_1", "error": None}])
    with pytest.raises(typer.Exit) as stopped:
        _fail_on_errors([{"config": "c", "domain": "B_1", "error": "invalid_input: no demonstration calls"}])
    assert stopped.value.exit_code == 1
    assert "B_1 (c): invalid_input: no demonstration calls" in capsys.readouterr().err

"""`precond convert openai`: OpenAI chat logs of a tool-calling agent → spec, programs, infer request.

Input: five real tau-bench airline trajectories (tests/fixtures/tau_airline/, four of them with state-changing
calls, three successful) and the domain's tool schemas; bad input is built from them by each test.
"""

from __future__ import annotations

import ast
import copy
import json
import re
from pathlib import Path
from typing import Any

import pytest

from precond.convert import openai as openai_converter
from precond.convert.shape import ConvertError
from precond_client.schemas import InferRequest
from tests.cli.inprocess import precond

ROOT = Path(__file__).resolve().parents[2]
TAU = ROOT / "tests" / "fixtures" / "tau_airline"


def records() -> list[dict[str, Any]]:
    return json.loads((TAU / "trajectories.json").read_text())


def tools() -> list[Any]:
    return json.loads((TAU / "tools.json").read_text())


def test_real_logs_become_a_spec_programs_and_a_request_whose_rules_need_the_read(tmp_path: Path) -> None:
    done = precond("convert", "openai", str(TAU / "trajectories.json"), "--tools", str(TAU / "tools.json"),
                   "--out", str(tmp_path), "--min-reward", "1")
    assert done.returncode == 0, done.stderr
    assert "5 trajectories" in done.stderr and "3 in" in done.stderr
    assert "1 without a state-changing call" in done.stderr
    spec = (tmp_path / "spec.py").read_text()
    assert "  def cancel_reservation(self, reservation_id):" in spec and "WRITES = ('book_reservation'," in spec
    program = (tmp_path / "demos" / "task5-trial1.py").read_text().splitlines()
    assert program[:2] == ["user = USER()", "agent = AGENT(user)"]
    read = program.index("agent.get_reservation_details('FQ8APE')")
    assert program[read + 1].startswith("agent.result('get_reservation_details', 'FQ8APE', True, {'reservation_id':")
    assert any(line.startswith("agent.update_reservation_baggages('FQ8APE', ") for line in program[read:])
    request = InferRequest.model_validate_json((tmp_path / "request.json").read_text())
    assert len(request.demonstrations) == 3 and "AGENT.cancel_reservation" in (request.actions or [])

    body = request.model_dump(mode="json")
    body["options"] = {"generators": ["enumerate"], "tolerance": 0, "ranking": "marginal"}
    inferred = precond("infer", "-", stdin=json.dumps(body))
    assert inferred.returncode == 0, inferred.stderr
    rules = json.loads(inferred.stdout)["preconditions"]
    for write in ("cancel_reservation", "update_reservation_flights", "update_reservation_baggages",
                  "update_reservation_passengers"):  # read before write, bound to the call's own reservation
        assert "reservation_id in self.results['get_reservation_details']" in rules[f"AGENT.{write}"], write


def test_results_pair_with_calls_by_position_and_stay_data() -> None:
    messages = [
        {"role": "system", "content": "policy"},
        {"role": "user", "content": "x'); import os; ('"},
        {"role": "assistant", "content": None, "tool_calls": [
            {"id": "same", "type": "function",
             "function": {"name": "get_reservation_details", "arguments": '{"reservation_id": "A1"}'}},
            {"id": "same", "type": "function",
             "function": {"name": "get_reservation_details", "arguments": '{"reservation_id": "B2"}'}}]},
        {"role": "tool", "tool_call_id": "same", "name": "get_reservation_details", "content": '{"cabin": "business"}'},
        {"role": "tool", "tool_call_id": "same", "name": "get_reservation_details", "content": "Error: not found"},
    ]
    converted = openai_converter.convert(messages, tools(), "t.json", "tools.json")
    assert converted.trajectories[0].program.splitlines()[2:] == [
        "user.says(\"x'); import os; ('\")",
        "agent.get_reservation_details('A1')",
        "agent.get_reservation_details('B2')",
        "agent.result('get_reservation_details', 'A1', True, {'cabin': 'business'})",
        "agent.result('get_reservation_details', 'B2', False, 'Error: not found')",
    ]
    assert converted.without_writes == 1


def _broken(change: Any) -> list[dict[str, Any]]:
    data = copy.deepcopy(records())
    change(data)
    return data


def _call_at(data: list[dict[str, Any]], record: int) -> tuple[int, dict[str, Any]]:
    traj = data[record]["traj"]
    index = next(i for i, m in enumerate(traj) if m.get("tool_calls"))
    return index, traj[index]["tool_calls"][0]["function"]


@pytest.mark.parametrize(("change", "expected"), [
    (lambda d: d[1]["traj"].__setitem__(3, "hello"), r"\[1\]\.traj\[3\]: not an OpenAI chat message"),
    (lambda d: _call_at(d, 2)[1].__setitem__("name", "delete_everything"),
     r"\[2\]\.traj\[\d+\]\.tool_calls\[0\]\.function\.name: no tool 'delete_everything'"),
    (lambda d: _call_at(d, 0)[1].__setitem__("arguments", '{"user_id": '),
     r"\[0\]\.traj\[\d+\]\.tool_calls\[0\]\.function\.arguments: not valid JSON"),
    (lambda d: d[3]["traj"].insert(2, {"role": "tool", "content": "{}"}),
     r"\[3\]\.traj\[2\]: a tool result that pairs with no call"),
    (lambda d: d[4]["traj"].__setitem__(1, {"role": "robot", "content": "hi"}),
     r"\[4\]\.traj\[1\]\.role: 'robot' is not an OpenAI role"),
])
def test_bad_input_names_the_trajectory_the_message_and_the_problem(change: Any, expected: str,
                                                                    tmp_path: Path) -> None:
    data = _broken(change)
    with pytest.raises(ConvertError, match=expected):
        openai_converter.convert(data, tools(), "trajectories.json", "tools.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(data))
    done = precond("convert", "openai", str(bad), "--tools", str(TAU / "tools.json"), "--out", str(tmp_path / "o"))
    assert done.returncode == 2 and done.stderr.startswith(f"error: {bad}: ["), done.stderr
    assert "Traceback" not in done.stderr


def test_a_file_that_is_no_trajectory_is_refused() -> None:
    with pytest.raises(ConvertError, match="expected a list of messages"):
        openai_converter.convert({"messages": []}, tools(), "t.json", "tools.json")
    with pytest.raises(ConvertError, match=r"tools\.json: expected a non-empty list of tool schemas"):
        openai_converter.convert(records(), {}, "t.json", "tools.json")


def test_precond_check_openai_judges_a_tool_call_after_the_messages(tmp_path: Path) -> None:
    converted = openai_converter.convert(records(), tools())
    (tmp_path / "spec.py").write_text(converted.spec)
    read = "reservation_id in self.results['get_reservation_details']"
    evidence = {"occurrences": 2, "holds": 2, "confidence": 0.34, "verdict": "thin", "decided": "assumed"}
    (tmp_path / "rules.json").write_text(json.dumps({"preconditions": {"AGENT.cancel_reservation": [read]},
                                                     "evidence": {"AGENT.cancel_reservation": {read: evidence}}}))
    (tmp_path / "history.json").write_text(json.dumps(records()[3]))  # a record: its messages are the history
    args = ["check", "--openai", str(tmp_path / "history.json"), "--spec", str(tmp_path / "spec.py"),
            "--rules", str(tmp_path / "rules.json")]
    done = precond(*args, "--call", '{"name": "cancel_reservation", "arguments": {"reservation_id": "H8Q05L"}}',
                   "--call", '{"name": "cancel_reservation", "arguments": "{\\"reservation_id\\": \\"NOPE00\\"}"}')
    assert done.returncode == 0, done.stderr
    read_one, unread = json.loads(done.stdout)["results"]
    assert read_one["allowed"] is True and read_one["call"] == "agent.cancel_reservation('H8Q05L')"
    assert unread["allowed"] is False and unread["violations"] == [read]
    # an infer response's evidence says how each rule was decided: every verdict says what it rests on
    assert read_one["rule_status"] == unread["rule_status"] == "assumed" and unread["decided"] == {read: "assumed"}
    bad = precond(*args, "--call", '{"name": "cancel_reservation", "arguments": {"id": 1}}')
    assert bad.returncode == 2 and "calls[0].arguments" in bad.stderr and "has no parameter 'id'" in bad.stderr


def test_what_a_log_carries_stays_literal_data() -> None:
    """Attack: quotes, newlines and code in every place a log puts text (user words, arguments, results):
    every statement of the program is a call whose arguments are literals, and the payload is a string."""
    payload = "x'); import os; os.system('id'); ('\n\"\"\"; __import__('os')._exit(3) #"
    messages = [
        {"role": "user", "content": payload},
        {"role": "assistant", "tool_calls": [{"function": {"name": "get_reservation_details",
                                                           "arguments": json.dumps({"reservation_id": payload})}}]},
        {"role": "tool", "content": json.dumps({"note": payload, payload: [payload]})},
        {"role": "assistant", "tool_calls": [{"function": {"name": "cancel_reservation",
                                                           "arguments": json.dumps({"reservation_id": payload})}}]},
        {"role": "tool", "content": "Error: " + payload},
    ]
    program = openai_converter.convert(messages, tools()).trajectories[0].program
    tree = ast.parse(program)
    for statement in tree.body[2:]:
        assert isinstance(statement, ast.Expr) and isinstance(statement.value, ast.Call)
        assert all(isinstance(ast.literal_eval(arg), object) for arg in statement.value.args)
    assert ast.literal_eval(tree.body[2].value.args[0]) == payload  # type: ignore[attr-defined]
    assert sum(isinstance(node, ast.Import) for node in ast.walk(tree)) == 0


@pytest.mark.parametrize(("schema", "expected"), [
    ({"name": "ｒｅｓｕｌｔ", "parameters": {"properties": {}}}, r"\.function\.name: 'result' is reserved"),
    ({"name": "ｌｏｏｋｕｐ", "parameters": {"properties": {"ｓｅｌｆ": {}}}},
     r"\.function\.parameters\.properties: parameter 'self' is reserved"),
    ({"name": "ｉｆ", "parameters": {"properties": {}}}, r"\.function\.name: tool name 'if' cannot be a Python name"),
])
def test_a_name_is_checked_as_python_reads_it(schema: dict[str, Any], expected: str) -> None:
    """Python reads identifiers NFKC-normalised: `def ｒｅｓｕｌｔ(self)` defines `result`, and a tool so named
    replaced the AGENT.result that records every tool's result. Names are normalised before they are checked."""
    with pytest.raises(ConvertError, match=expected):
        openai_converter.read_tools([*tools(), schema], "tools.json")


def test_a_tool_named_with_other_letters_is_the_same_tool() -> None:
    spec = openai_converter.convert(records()[:1], [*tools(), {"name": "ｌｏｏｋｕｐ"}]).spec
    methods = [n.name for n in ast.walk(ast.parse(spec)) if isinstance(n, ast.FunctionDef)]
    assert "lookup" in methods and methods.count("result") == 1
    renderer = openai_converter.Renderer(openai_converter.spec_tools(spec, "calls"), "calls")
    assert renderer.line({"name": "ｌｏｏｋｕｐ", "arguments": {}}, "calls[0]") == "agent.lookup()"


@pytest.mark.parametrize(("text", "says"), [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    (json.dumps([{"traj": [], "reward": 10 ** 400}]), r"\[0\]\.reward: not a finite number"),
    ("[" + "1" * 5000 + "]", "not JSON"),
])
def test_json_the_cli_cannot_use_exits_2_with_a_message(tmp_path: Path, text: str, says: str) -> None:
    """Every command that reads a user's JSON file: the converter, a check's OpenAI messages, prior rules."""
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    (tmp_path / "spec.py").write_text(openai_converter.convert(records()[:1], tools()).spec)
    call = '{"name": "think", "arguments": {"thought": "x"}}'
    for args, where in (
        (("convert", "openai", str(bad), "--tools", str(TAU / "tools.json"), "--out", str(tmp_path / "o")), f"{bad}"),
        (("check", "--openai", str(bad), "--spec", str(tmp_path / "spec.py"), "--call", call), f"{bad}"),
        (("infer", str(ROOT / "examples" / "infer-enumerate.json"), "--prior-rules", str(bad)), f"--prior-rules {bad}"),
    ):
        done = precond(*args)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
        if "reward" not in says or args[0] == "convert":  # only the converter reads rewards
            assert done.stderr.startswith(f"error: {where}") and re.search(says, done.stderr), done.stderr

"""`precond mcp` as an agent team runs it: the refund desk of examples/mcp (a real MCP server, the SDK's
`MCPServer`) behind the proxy, driven by the SDK's own client over stdio and over streamable HTTP on loopback;
what it records converts and learns with no editing, and what it refuses never reaches the upstream."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Iterator, Sequence
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path
from typing import Any

import pytest
from mcp import ClientSession, StdioServerParameters, stdio_client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared.exceptions import MCPError

from precond.engine.factory import build_engine
from precond.stack.keyed import KeyedStack
from precond_client import Client
from precond_client.guard import Guard
from precond_client.mcp.recorder import CUT, Recording
from precond_client.mcp.tools import spec_for
from precond_client.schemas import InferRequest

pytestmark = pytest.mark.stack  # starts the proxy and MCP servers as processes

ROOT = Path(__file__).resolve().parents[2]
DESK = f"{sys.executable} {ROOT / 'examples' / 'mcp' / 'refund_desk.py'}"
FAULTY = f"{sys.executable} {Path(__file__).parent / 'mcp_faulty_server.py'}"
REFUND_RULES = {"AGENT.refund_order": ["order_id in self.results['get_order']"], "AGENT.send_note": []}
Calls = Sequence[tuple[str, dict[str, Any]]]


def proxy_args(log: Path, *extra: str, upstreams: Sequence[str] = (DESK,)) -> list[str]:
    return ["-m", "precond.cli", "mcp", *(a for u in upstreams for a in ("--upstream", u)), "--log", str(log),
            *extra]


@asynccontextmanager
async def stdio_proxy(args: list[str]) -> AsyncIterator[ClientSession]:
    params = StdioServerParameters(command=sys.executable, args=args, cwd=str(ROOT))
    async with stdio_client(params) as (read, write), ClientSession(read, write) as session:
        await session.initialize()
        yield session


def texts(result: Any) -> str:
    return "".join(block.text for block in result.content)


def records(log: Path) -> list[dict[str, Any]]:
    return [json.loads(p.read_text()) for p in sorted((log / "sessions").glob("*.json"))]


def call_lines(log: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (log / "calls.jsonl").read_text().splitlines()]


def test_enforce_over_stdio_refuses_a_call_the_rules_forbid_before_the_upstream(tmp_path: Path) -> None:
    rules = tmp_path / "rules.json"
    rules.write_text(json.dumps(REFUND_RULES))
    log = tmp_path / "log"

    async def run() -> tuple[Any, Any, Any, Any]:
        async with stdio_proxy(proxy_args(log, "--mode", "enforce", "--rules", str(rules))) as session:
            listed = await session.list_tools()
            refused = await session.call_tool("refund_order", {"order_id": "A100", "amount": 40})
            read = await session.call_tool("get_order", {"order_id": "A100"})
            allowed = await session.call_tool("refund_order", {"order_id": "A100", "amount": 5})
            return listed, refused, read, allowed

    listed, refused, read, allowed = asyncio.run(run())
    assert [t.name for t in listed.tools] == ["get_order", "refund_order", "send_note"]
    assert refused.is_error
    assert "order_id in self.results['get_order']" in texts(refused)  # the rule, and what would make it hold
    assert "The tool did not run" in texts(refused) and "Call get_order for order_id first" in texts(refused)
    assert json.loads(texts(read))["refunded"] == 0  # the refused refund never reached the desk
    assert not allowed.is_error and json.loads(texts(allowed))["refunded"] == 5
    [record] = records(log)
    traj = record["traj"]
    assert [m["role"] for m in traj] == ["assistant", "tool"] * 3
    assert traj[1]["content"].startswith("Error: the precondition guard")
    verdicts = [line["verdict"]["allowed"] for line in call_lines(log)]
    assert verdicts == [False, True, True]
    assert [line["outcome"] for line in call_lines(log)] == ["refused", "ok", "ok"]



def test_a_call_answered_beside_the_sdk_is_answered_as_the_sdk_answers_it(tmp_path: Path) -> None:
    """Differential: each call made plainly (answered by the proxy beside the SDK's server) and again with a
    `_meta` (which only the SDK's server reads), in one session: the same result, refusal or MCP error."""
    rules = tmp_path / "rules.json"
    rules.write_text(json.dumps(REFUND_RULES))
    calls: Calls = [("get_order", {"order_id": "A100"}), ("get_order", {"order_id": "X1"}),
                    ("refund_order", {"order_id": "A300", "amount": 1}), ("send_note", {"order_id": "A1", "text": "é"}),
                    ("echo", {"text": "hi"}), ("malformed", {}), ("no_such_tool", {})]

    async def answered(session: ClientSession, name: str, arguments: dict[str, Any], meta: Any) -> Any:
        try:
            return (await session.call_tool(name, arguments, meta=meta)).model_dump()
        except MCPError as exc:
            return exc.error.model_dump()

    async def run() -> list[tuple[Any, Any]]:
        args = proxy_args(tmp_path / "log", "--mode", "enforce", "--rules", str(rules), "--timeout", "5",
                          upstreams=[DESK, FAULTY])
        async with stdio_proxy(args) as session:
            return [(await answered(session, name, arguments, None),
                     await answered(session, name, arguments, {"progressToken": "sdk"}))
                    for name, arguments in calls]

    pairs = asyncio.run(run())
    for (plain, sdk), (name, _) in zip(pairs, calls, strict=True):
        assert plain == sdk, name
    assert pairs[2][0]["is_error"] and "order_id in self.results['get_order']" in pairs[2][0]["content"][0]["text"]
    assert pairs[5][0]["message"].startswith(f"upstream {FAULTY!r} answered a malformed result")
    assert pairs[6][0]["message"] == "no tool 'no_such_tool' in the upstreams"
    assert len(call_lines(tmp_path / "log")) == 2 * (len(calls) - 1)  # every call but the unknown tool's, logged

def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextmanager
def serving(args: list[str], port: int) -> Iterator[str]:
    """A process serving streamable HTTP on 127.0.0.1:port, until the block ends (then stopped and waited for)."""
    process = subprocess.Popen([sys.executable, *args], cwd=ROOT, stdin=subprocess.DEVNULL,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while True:
            assert process.poll() is None, process.stderr.read().decode() if process.stderr else ""
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "not serving after 120 s"
                time.sleep(0.2)
        yield f"http://127.0.0.1:{port}/mcp"
    finally:
        process.terminate()
        process.wait(timeout=30)
        if process.stderr:
            process.stderr.close()


@asynccontextmanager
async def http_session(url: str) -> AsyncIterator[ClientSession]:
    async with streamable_http_client(url) as (read, write), ClientSession(read, write) as session:
        await session.initialize()
        yield session


async def play(session: ClientSession, calls: Calls) -> list[Any]:
    return [await session.call_tool(name, arguments) for name, arguments in calls]


CAREFUL = [  # a careful agent's sessions: every refund and note reads its order first
    [("get_order", {"order_id": "A100"}), ("refund_order", {"order_id": "A100", "amount": 5}),
     ("send_note", {"order_id": "A100", "text": "refunded"})],
    [("get_order", {"order_id": "A200"}), ("get_order", {"order_id": "A300"}),
     ("refund_order", {"order_id": "A300", "amount": 10})],
    [("get_order", {"order_id": "A200"}), ("refund_order", {"order_id": "A200", "amount": 25}),
     ("send_note", {"order_id": "A200", "text": "done"})],
    [("get_order", {"order_id": "A100"}), ("send_note", {"order_id": "A100", "text": "on its way"}),
     ("refund_order", {"order_id": "A100", "amount": 1})],
]
CARELESS = [("refund_order", {"order_id": "A300", "amount": 90}), ("get_order", {"order_id": "A300"}),
            ("refund_order", {"order_id": "A300", "amount": 3}), ("send_note", {"order_id": "A100", "text": "hi"})]


def precond(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "precond.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def learn(log: Path, out: Path, labels: Path | None = None) -> dict[str, Any]:
    """`precond convert openai` on the recorded sessions as they are, then the model-free inference."""
    converted = precond("convert", "openai", str(log / "sessions"), "--tools", str(log / "tools.json"),
                        "--out", str(out), *(["--labels", str(labels)] if labels else []))
    assert converted.returncode == 0, converted.stderr
    body = json.loads((out / "request.json").read_text())
    body["options"] = {**body.get("options", {}), "generators": ["enumerate"]}
    response = build_engine(with_model=False).infer(InferRequest.model_validate(body))
    return json.loads(response.model_dump_json())


@pytest.fixture(scope="module")
def learned(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Sessions recorded through the proxy on streamable HTTP (one MCP session each), learned from: the log
    folder and the rules file (what `precond infer` prints)."""
    root = tmp_path_factory.mktemp("learned")
    log = root / "log"
    with serving(proxy_args(log, "--http", str(port := free_port())), port) as url:
        async def record() -> None:
            for calls in CAREFUL:
                async with http_session(url) as session:
                    await play(session, calls)
        asyncio.run(record())
    response = learn(log, root / "converted")
    rules = root / "response.json"
    rules.write_text(json.dumps(response))
    return log, rules


def test_recorded_sessions_convert_and_learn_with_no_editing(learned: tuple[Path, Path]) -> None:
    log, rules = learned
    sessions = records(log)
    assert len(sessions) == len(CAREFUL)  # one record per MCP session
    assert all(len(s["traj"]) == 2 * len(calls) for s, calls in zip(sessions, CAREFUL, strict=True))
    preconditions = json.loads(rules.read_text())["preconditions"]
    assert "order_id in self.results['get_order']" in preconditions["AGENT.refund_order"]
    # the spec the proxy judges --rules over is the converter's, character for character
    schemas = json.loads((log / "tools.json").read_text())
    assert spec_for(schemas) == (log.parent / "converted" / "spec.py").read_text()


def test_a_folder_of_sessions_with_a_bad_one_is_refused_naming_its_file(tmp_path: Path) -> None:
    (tmp_path / "sessions").mkdir()
    good = {"task_id": "a", "trial": 0, "traj": [{"role": "user", "content": "hi"}]}
    (tmp_path / "sessions" / "a.json").write_text(json.dumps(good))
    (tmp_path / "sessions" / "b.json").write_text(json.dumps({**good, "traj": [{"content": "no role"}]}))
    (tmp_path / "tools.json").write_text(json.dumps([{"type": "function", "function": {"name": "get_order"}}]))
    result = precond("convert", "openai", str(tmp_path / "sessions"), "--tools", str(tmp_path / "tools.json"),
                     "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert f"{tmp_path / 'sessions' / 'b.json'}: traj[0]: not an OpenAI chat message" in result.stderr


def guard_of(log: Path, rules: Path) -> Guard:
    """The embedded guard as a user builds it from `precond convert openai`'s spec and the inference."""
    spec = (log.parent / "converted" / "spec.py").read_text()
    loaded = json.loads(rules.read_text())
    decided = {a: {r: e["decided"] for r, e in found.items()} for a, found in loaded["evidence"].items()}
    return Guard(spec, loaded["preconditions"], decided)


def test_enforce_and_shadow_give_the_embedded_guards_verdicts_on_the_same_history(
        learned: tuple[Path, Path], tmp_path: Path) -> None:
    """Differential: each verdict either mode logged is the embedded guard's on the recorded history before the
    call. Enforce over stdio with a stdio upstream; shadow over stdio with the desk on streamable HTTP."""
    log, rules = learned
    guard = guard_of(log, rules)
    enforce_log, shadow_log = tmp_path / "enforce", tmp_path / "shadow"

    async def enforce() -> list[Any]:
        async with stdio_proxy(proxy_args(enforce_log, "--mode", "enforce", "--rules", str(rules))) as session:
            return await play(session, CARELESS)

    enforced = asyncio.run(enforce())
    port = free_port()
    with serving([str(ROOT / "examples" / "mcp" / "refund_desk.py"), "--http", str(port)], port) as desk:
        async def shadow() -> list[Any]:
            args = proxy_args(shadow_log, "--mode", "shadow", "--rules", str(rules), upstreams=[desk])
            async with stdio_proxy(args) as session:
                return await play(session, CARELESS)
        shadowed = asyncio.run(shadow())

    assert [r.is_error for r in enforced] == [True, False, False, True]  # the unread refund and note, refused
    assert not any(r.is_error for r in shadowed)  # shadow never blocks
    assert json.loads(texts(shadowed[1]))["refunded"] == 90  # the refund shadow let through happened
    for folder in (enforce_log, shadow_log):
        [record] = records(folder)
        logged = call_lines(folder)
        assert len(logged) == len(CARELESS)
        for n, (line, (name, arguments)) in enumerate(zip(logged, CARELESS, strict=True)):
            expected = guard.session(record["traj"][: 2 * n]).check(name, arguments)
            assert line["verdict"]["allowed"] == expected.allowed, (folder.name, n)
            assert line["verdict"]["violations"] == expected.violations
            assert line["verdict"]["call"] == expected.call
    assert call_lines(shadow_log)[0]["verdict"]["allowed"] is False


def test_a_stored_set_is_judged_by_the_service(learned: tuple[Path, Path], keyed: KeyedStack,
                                               tmp_path: Path) -> None:
    """`--set ps_...@n --server URL`: each call a `/check-actions` of the session's messages (`ServiceGuard`)."""
    log, _ = learned
    spec = spec_for(json.loads((log / "tools.json").read_text()))
    with Client(keyed.url, api_key=keyed.keys["guard"]) as service:
        reference = service.create_set({"spec": spec, "preconditions": REFUND_RULES}).reference
    args = proxy_args(tmp_path / "log", "--mode", "enforce", "--set", reference, "--server", keyed.url,
                      "--api-key", keyed.keys["guard"])

    async def run() -> list[Any]:
        async with stdio_proxy(args) as session:
            return await play(session, CARELESS[:3])

    results = asyncio.run(run())
    assert [r.is_error for r in results] == [True, False, False]
    assert f"the precondition guard ({reference}) refused agent.refund_order('A300', 90)" in texts(results[0])
    assert [line["verdict"]["allowed"] for line in call_lines(tmp_path / "log")] == [False, True, True]


def _tool_of(session: dict[str, Any], index: int) -> str | None:
    """The tool the message at `index` of a recorded session calls (None: no call there)."""
    calls = session["traj"][index].get("tool_calls") or [{}]
    return calls[0].get("function", {}).get("name")


def test_a_labelled_call_becomes_a_counterexample_of_the_next_version(learned: tuple[Path, Path],
                                                                      tmp_path: Path) -> None:
    log, _ = learned
    first = next(path for path in sorted((log / "sessions").glob("*.json"))  # the sessions' order is not the
                 if _tool_of(json.loads(path.read_text()), 2) == "refund_order")  # order they were played in
    labels = tmp_path / "labels.json"
    marked = precond("label", str(first), "--call", "call_2", "--labels", str(labels), "--note", "refund twice")
    assert marked.returncode == 0, marked.stderr
    [entry] = json.loads(labels.read_text())
    assert (entry["message_index"], entry["tool"], entry["allowed"]) == (2, "refund_order", False)
    response = learn(log, tmp_path / "next", labels)
    request = json.loads((tmp_path / "next" / "request.json").read_text())
    [run] = request["counterexamples"]
    assert run["calls"][0]["verdict"] == "refuse" and run["calls"][0]["name"].endswith(": [0]")
    assert "AGENT.refund_order" in response["preconditions"]
    missing = precond("label", str(first), "--call", "call_99", "--labels", str(labels))
    assert missing.returncode == 2 and "no call 'call_99'" in missing.stderr


def test_a_dead_hung_or_malformed_upstream_is_an_error_naming_it_no_call_is_lost_and_a_dead_one_restarts(
        tmp_path: Path) -> None:
    log = tmp_path / "log"
    calls = ["echo", "malformed", "hang", "echo", "die", "echo"]

    async def run() -> tuple[list[str], Any]:
        said = []
        async with stdio_proxy(proxy_args(log, "--timeout", "2", upstreams=[FAULTY, DESK])) as session:
            for name in calls:
                try:
                    said.append(texts(await session.call_tool(name, {"text": "hi"})))
                except MCPError as exc:
                    said.append(exc.message)
            return said, await session.call_tool("get_order", {"order_id": "A100"})

    said, desk = asyncio.run(run())
    named = f"upstream {FAULTY!r}"
    assert said[0] == said[3] == "hi"
    assert said[1].startswith(f"{named} answered a malformed result")
    assert said[2] == f"{named} did not answer within 2 s (--timeout)"
    assert said[4].startswith(f"{named} is gone")
    assert said[5] == "hi"  # the upstream that died was started again for the next call
    assert not desk.is_error  # the proxy stayed up: the other upstream still serves
    [record] = records(log)
    assert len(record["traj"]) == 2 * (len(calls) + 1)  # every call recorded, each failure as an error
    assert [m["content"].startswith("Error") for m in record["traj"][1:12:2]] == [
        False, True, True, False, True, False]
    assert [line["outcome"] for line in call_lines(log)] == [
        "ok", "upstream failed", "upstream failed", "ok", "upstream failed", "ok", "ok"]


def test_a_session_log_is_bounded_and_a_call_past_the_bound_is_refused_named(tmp_path: Path) -> None:
    log = tmp_path / "log"
    note = "x" * 25_000  # two such calls fit in 64 KiB, a third does not

    async def run() -> list[Any]:
        async with stdio_proxy(proxy_args(log, "--max-log-bytes", "65536")) as session:
            return await play(session, [("send_note", {"order_id": "A100", "text": note})] * 4)

    results = asyncio.run(run())
    assert [r.is_error for r in results] == [False, False, True, True]
    assert "--max-log-bytes" in texts(results[2]) and "65536 bytes" in texts(results[2])
    [record] = records(log)
    assert len(record["traj"]) == 4 and (log / "sessions").stat().st_mode & 0o077 == 0
    assert sum(p.stat().st_size for p in (log / "sessions").glob("*.json")) <= 65536
    assert [line["outcome"] for line in call_lines(log)][2:] == ["refused: log full"] * 2


def test_calls_jsonl_at_its_bound_refuses_the_call_named_until_the_file_is_moved_away(tmp_path: Path) -> None:
    log = tmp_path / "log"
    log.mkdir()
    (log / "calls.jsonl").write_text("{}\n" * 20_000)  # 60 KB of 64 KiB: no room for a call's line
    stderr = tmp_path / "stderr"

    async def run() -> list[Any]:
        params = StdioServerParameters(command=sys.executable, cwd=str(ROOT),
                                       args=proxy_args(log, "--max-calls-bytes", "65536"))
        with stderr.open("w") as errlog:
            async with stdio_client(params, errlog=errlog) as (read, write), ClientSession(read, write) as session:
                await session.initialize()
                first = await play(session, [("get_order", {"order_id": "A100"})] * 2)
                (log / "calls.jsonl").rename(log / "calls.1.jsonl")
                return [*first, *await play(session, [("get_order", {"order_id": "A100"})])]

    refused, again, made = asyncio.run(run())
    assert refused.is_error and again.is_error and not made.is_error
    assert "calls.jsonl reached its bound (65536 bytes, --max-calls-bytes)" in texts(refused)
    assert stderr.read_text().count("calls.jsonl reached its bound") == 1  # said once on the proxy's stderr
    assert [line["outcome"] for line in call_lines(log)] == ["ok"]
    [record] = records(log)
    assert len(record["traj"]) == 2  # the refused calls were not made, nor recorded


@pytest.mark.parametrize(("args", "said"), [
    (["--mode", "enforce"], "--mode enforce needs the rules"),
    (["--mode", "record", "--rules", "x.json"], "--mode record judges nothing"),
    (["--mode", "veto"], "--mode: 'veto' is not one of"),
    (["--mode", "shadow", "--set", "ps_1@1"], "--set needs --server"),
    (["--mode", "enforce", "--rules", "missing.json"], "--rules: cannot read missing.json"),
])
def test_bad_options_exit_2_naming_the_option(tmp_path: Path, args: list[str], said: str) -> None:
    result = precond("mcp", "--upstream", DESK, "--log", str(tmp_path / "log"), *args)
    assert result.returncode == 2 and said in result.stderr, result.stderr


def test_a_tool_two_upstreams_list_is_refused_at_start_naming_both(tmp_path: Path) -> None:
    result = precond("mcp", "--upstream", FAULTY, "--upstream", FAULTY + " ", "--log", str(tmp_path / "log"))
    assert result.returncode == 2
    assert f"tool 'echo' is listed by two upstreams, {FAULTY!r} and {FAULTY + ' '!r}" in result.stderr


def test_rules_for_tools_the_upstreams_lack_are_refused_at_start(tmp_path: Path) -> None:
    rules = tmp_path / "rules.json"
    rules.write_text(json.dumps({"AGENT.delete_everything": ["True"]}))
    result = precond("mcp", "--upstream", DESK, "--log", str(tmp_path / "log"), "--mode", "enforce",
                     "--rules", str(rules))
    assert result.returncode == 2 and "AGENT.delete_everything: not a tool of the spec" in result.stderr


SERVE = """
import json, sys
from pathlib import Path
import anyio
from precond_client.guard import Guard
from precond_client.mcp.serve import Settings, serve
from precond_client.mcp.tools import spec_for
rules = json.loads(Path(sys.argv[3]).read_text())
anyio.run(serve, Settings([sys.argv[1]], "enforce", Path(sys.argv[2])),
          lambda schemas: Guard(spec_for(schemas), rules))
"""
"""The proxy as `precond mcp --mode enforce --rules` makes it, with the light client alone (no service code)."""


@pytest.fixture()
def open_folder() -> Iterator[Path]:
    """A folder any user can write to (pytest's own are private to root, which nobody cannot cross)."""
    folder = Path(tempfile.mkdtemp(prefix="precond-mcp-"))
    folder.chmod(0o777)
    try:
        yield folder
    finally:
        shutil.rmtree(folder)


@pytest.mark.parametrize("user", ["root", "nobody"])
def test_hostile_arguments_and_results_are_data_and_the_log_is_private_as_root_or_not(
        user: str, open_folder: Path) -> None:
    """Code in a call's arguments and in an upstream's answer (the desk's error repeats the order id) is recorded
    and judged as data: nothing runs, the refused call never reaches the desk, and only the proxy's user can
    read what it recorded (folder 0700, files 0600: the kernel enforces it)."""
    if user == "nobody" and os.geteuid() != 0:
        pytest.skip("already not root: the root case ran as this user")
    tmp_path = open_folder
    canary = tmp_path / "pwned"
    touch = f"__import__('pathlib').Path({str(canary)!r}).touch()"
    rules = tmp_path / "rules.json"
    rules.write_text(json.dumps(REFUND_RULES))
    rules.chmod(0o644)
    log = tmp_path / "log"
    prefix = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] if user == "nobody" else []
    port = free_port()  # the desk on streamable HTTP, served by this test's user: the proxy's user only calls it
    desk = serving([str(ROOT / "examples" / "mcp" / "refund_desk.py"), "--http", str(port)], port)
    hostile = f"'); {touch}; ('"

    async def run(url: str) -> list[Any]:
        args = [*prefix, sys.executable, "-c", SERVE, url, str(log), str(rules)]
        params = StdioServerParameters(command=args[0], args=args[1:], cwd=str(tmp_path),
                                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
        async with stdio_client(params) as (read, write), ClientSession(read, write) as session:
            await session.initialize()
            return await play(session, [("refund_order", {"order_id": hostile, "amount": 1}),
                                        ("get_order", {"order_id": hostile}),
                                        ("refund_order", {"order_id": hostile, "amount": 1})])

    with desk as url:
        refused, read, refunded = asyncio.run(run(url))
    assert refused.is_error and "The tool did not run" in texts(refused)
    assert read.is_error and hostile in texts(read)  # the desk's own error, repeating the id
    assert refunded.is_error and "The tool did not run" in texts(refunded)  # a failed read is no read
    assert not canary.exists()
    [record] = records(log)
    assert json.loads(record["traj"][2]["tool_calls"][0]["function"]["arguments"])["order_id"] == hostile
    made = [log, log / "sessions", *(log / "sessions").iterdir(), log / "calls.jsonl", log / "tools.json"]
    assert all(path.stat().st_mode & 0o077 == 0 for path in made)
    assert {path.stat().st_uid for path in made} == {os.geteuid() if user == "root" else 65534}


def test_an_upstream_that_does_not_start_exits_2_naming_it(tmp_path: Path) -> None:
    result = precond("mcp", "--upstream", "false", "--log", str(tmp_path / "log"))
    assert result.returncode == 2 and "upstream 'false' did not start" in result.stderr, result.stderr
    unreachable = f"http://127.0.0.1:{free_port()}/mcp"
    result = precond("mcp", "--upstream", unreachable, "--log", str(tmp_path / "log"))
    assert result.returncode == 2 and f"upstream {unreachable!r} did not start" in result.stderr, result.stderr


def test_an_http_upstream_that_goes_away_is_an_error_naming_it_and_the_proxy_stays_up(tmp_path: Path) -> None:
    """The SDK's HTTP transport ends its task group with the refused connection: that ends the upstream's
    connection, never the proxy."""
    port = free_port()
    log = tmp_path / "log"

    async def run(url: str, desk: subprocess.Popen[bytes]) -> tuple[Any, str, str, Any]:
        async with stdio_proxy(proxy_args(log, "--timeout", "20", upstreams=[url, FAULTY])) as session:
            before = await session.call_tool("get_order", {"order_id": "A100"})
            desk.terminate()
            desk.wait(timeout=30)
            said = []
            for _ in range(2):
                try:
                    await session.call_tool("get_order", {"order_id": "A100"})
                    said.append("answered")
                except MCPError as exc:
                    said.append(exc.message)
            return before, said[0], said[1], await session.call_tool("echo", {"text": "still here"})

    process = subprocess.Popen([sys.executable, str(ROOT / "examples" / "mcp" / "refund_desk.py"), "--http",
                                str(port)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        url = f"http://127.0.0.1:{port}/mcp"
        deadline = time.monotonic() + 120
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline
                time.sleep(0.2)
        before, first, second, echoed = asyncio.run(run(url, process))
    finally:
        process.kill()
        process.wait(timeout=30)
    assert not before.is_error
    assert first.startswith(f"upstream {url!r} "), first
    assert second.startswith(f"upstream {url!r} is gone") and "did not start again" in second, second
    assert texts(echoed) == "still here"
    [record] = records(log)
    assert len(record["traj"]) == 8


def test_a_result_too_long_for_the_room_left_is_recorded_cut_and_the_record_stays_within_its_bound(
        tmp_path: Path) -> None:
    recording = Recording.start(tmp_path, "s", 65536)
    call_id, _ = recording.call("send_note", {"order_id": "A100", "text": "x" * 45_000})  # 19 KB left
    recording.result(call_id, "send_note", "ü" * 20_000)
    record = json.loads((tmp_path / "s.json").read_text(encoding="utf-8"))
    assert (tmp_path / "s.json").stat().st_size <= 65536
    assert record["traj"][1]["content"].endswith(CUT) and record["traj"][1]["content"].startswith("üü")

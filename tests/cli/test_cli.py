"""The `precond` console script as a user runs it: a real process, JSON on stdout, errors on stderr."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import pytest

from tests.cli.inprocess import precond

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def test_infer_prints_preconditions_and_a_runnable_program() -> None:
    result = precond("infer", str(EXAMPLES / "infer-enumerate.json"))
    assert result.returncode == 0, result.stderr
    body = json.loads(result.stdout)
    assert "self.user.requested_slot[slot]" in body["preconditions"]["SYSTEM.INFORM"]
    assert "assert self.user.no_more" in body["program"]
    assert body["stats"]["total"]["kept"] > 0


def test_infer_prints_the_exceptions_of_kept_rules_on_stderr() -> None:
    data = json.loads((ROOT / "tests" / "fixtures" / "data" / "sgd" / "Restaurants_1.json").read_text())
    demos = [d["program"] for d in data["demos"]]
    demo = demos[0].splitlines()
    at = next(i for i, line in enumerate(demo) if line.startswith("user.INFORM('"))
    slot = demo[at].split("'")[1]
    demo.insert(at + 1, f"system.REQUEST('{slot}')")  # an agent's slip: re-asks what the user just said
    demos[0] = "\n".join(demo) + "\n"
    request = {"spec": data["spec_program"], "demonstrations": demos, "options": {"generators": ["enumerate"]}}
    result = precond("infer", "-", stdin=json.dumps(request))
    assert result.returncode == 0, result.stderr
    assert "SYSTEM.REQUEST: `not self.user.informed_slot[slot]` holds at" in result.stderr
    assert f"  demonstrations[0], line {at + 2}: system.REQUEST('{slot}')" in result.stderr
    assert json.loads(result.stdout)["evidence"]["SYSTEM.REQUEST"]["not self.user.informed_slot[slot]"]


def test_infer_can_leave_candidates_out_and_print_a_summary_to_read(tmp_path: Path) -> None:
    body = json.loads((EXAMPLES / "infer-enumerate.json").read_text())
    body["options"]["library"] = False  # what the two demonstrations alone give (the library: test_library.py)
    example = tmp_path / "infer-enumerate.json"
    example.write_text(json.dumps(body))
    full = precond("infer", str(example), "--candidates", "all")
    kept = precond("infer", str(example))  # the default: the kept rules' reports
    assert full.returncode == 0 and kept.returncode == 0, kept.stderr
    everything, few = json.loads(full.stdout), json.loads(kept.stdout)
    assert few["preconditions"] == everything["preconditions"] and few["evidence"] == everything["evidence"]
    assert few["warnings"] == everything["warnings"]
    assert {a: sorted(c["assertion"] for c in cs) for a, cs in few["candidates"].items()} == {
        a: sorted(rules) for a, rules in everything["preconditions"].items()}
    assert len(kept.stdout) * 10 < len(full.stdout)  # 19 KB instead of 490 KB
    summary = precond("infer", str(example), "--summary")
    assert summary.returncode == 0, summary.stderr
    lines = summary.stdout.splitlines()
    at = lines.index("SYSTEM.REQUEST: 1 rule(s), all must hold")
    assert lines[at + 1] == "  not self.user.informed_slot[slot]"
    assert lines[at + 2] == "    evidence: held, holds at 5 of 5 demonstrated calls (confidence 0.65)"
    # 5 calls in 2 demonstrations: too few dialogs to establish it; the reason it shares with other rules is
    # said once, first, and named by its number at each of them
    shared = {line.split("] ", 1)[0] + "]": line.split("] ", 1)[1] for line in lines if line.startswith("[")}
    assert lines[at + 3].startswith("    decided: assumed: [") and lines[at + 3].endswith("]")
    reason = shared[lines[at + 3].rsplit(" ", 1)[1]]
    assert reason.startswith("kept: held at every occurrence")
    assert sum(reason in line for line in lines) == 1
    assert len(shared) == len(set(shared.values())) and all(
        sum(line.endswith(f" {n}") for line in lines) > 1 for n in shared)
    assert lines[at + 4].startswith("  WARNING thin evidence: SYSTEM.REQUEST is called 5 time(s)")
    at = lines.index("SYSTEM.NOTIFY_FAILURE: 1 rule(s), all must hold")  # never demonstrated: refused
    assert lines[at + 1] == "  False" and lines[at + 3].startswith("    decided: unseen: ")
    assert lines[-1].startswith(f"{sum(map(len, everything['preconditions'].values()))} rule(s) for 12 action(s)")


def test_infer_takes_prior_rules_from_files_and_names_them(tmp_path: Path) -> None:
    """Another service's answer as priors: NOTIFY_FAILURE, never demonstrated here, takes its rule."""
    other = tmp_path / "buses.json"
    other.write_text(json.dumps({"preconditions": {"SYSTEM.NOTIFY_FAILURE": ["not self.query_success"]}}))
    summary = precond("infer", str(EXAMPLES / "infer-enumerate.json"), "--summary", "--prior-rules", str(other))
    assert summary.returncode == 0, summary.stderr
    lines = summary.stdout.splitlines()
    at = lines.index("SYSTEM.NOTIFY_FAILURE: 1 rule(s), all must hold")
    assert lines[at + 1] == "  not self.query_success"
    assert lines[at + 3].startswith("    decided: transferred (from buses.json): ")
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({"SYSTEM.GOODBYE": [1]}))
    refused = precond("infer", str(EXAMPLES / "infer-enumerate.json"), "--prior-rules", str(broken))
    assert refused.returncode == 2 and "--prior-rules" in refused.stderr and "broken.json" in refused.stderr


def test_an_operator_key_is_marked_in_the_file_and_the_list(tmp_path: Path) -> None:
    from precond.gateway.api_keys import read_records

    keys = tmp_path / "keys.jsonl"
    for extra in ([], ["--operator"]):
        made = subprocess.run([sys.executable, "-m", "precond.cli", "keys", "create", "--tenant", "ops", "--file",
                               str(keys), *extra], capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert made.returncode == 0, made.stderr
    assert [r.operator for r in read_records(keys)] == [False, True]
    listed = subprocess.run([sys.executable, "-m", "precond.cli", "keys", "list", "--file", str(keys)],
                            capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert [line.endswith("\toperator") for line in listed.stdout.splitlines()] == [False, True]


def test_check_reads_standard_input() -> None:
    request = json.loads((EXAMPLES / "check-actions.json").read_text())
    request["calls"].append("system.GOODBYE()")  # no precondition given for GOODBYE: allowed
    result = precond("check", "-", stdin=json.dumps(request))
    assert result.returncode == 0, result.stderr
    verdicts = json.loads(result.stdout)["results"]
    assert [v["call"] for v in verdicts] == request["calls"]
    assert verdicts[-1]["allowed"] and not verdicts[0]["allowed"] and verdicts[0]["violations"]
    # rules sent without how they were decided are "given"; GOODBYE has none: allowed, and nothing is known
    assert verdicts[0]["rule_status"] == "given" and verdicts[-1]["rule_status"] == "missing"


def test_bad_request_exits_2_naming_the_field() -> None:
    bad = json.dumps({"spec": "class A:\n  def f(self): pass\n", "demonstrations": [], "options": {"sedd": 1}})
    result = precond("infer", "-", stdin=bad)
    assert result.returncode == 2
    assert "demonstrations" in result.stderr and "sedd" in result.stderr and result.stdout == ""
    assert "  options.sedd: Extra inputs are not permitted" in result.stderr.splitlines()
    neither = precond("check", "-", stdin=json.dumps({"history": "", "calls": ["a.b()"]}))
    assert neither.returncode == 2
    assert "  body: give `spec` (with `preconditions`) or `precondition_set`" in neither.stderr.splitlines()


def test_program_error_exits_2_with_line() -> None:
    request = json.loads((EXAMPLES / "infer-enumerate.json").read_text())
    request["demonstrations"][0] += "system.DANCE()\n"
    result = precond("infer", "-", stdin=json.dumps(request))
    assert result.returncode == 2
    assert "demonstrations[0]" in result.stderr and "AttributeError" in result.stderr


def test_missing_file_is_a_clear_error() -> None:
    result = precond("infer", "/nonexistent/request.json")
    assert result.returncode == 2 and "cannot read" in result.stderr


def test_eval_without_data_names_the_path_and_the_setting(tmp_path: Path) -> None:
    missing = tmp_path / "no-data"
    result = subprocess.run(
        [sys.executable, "-m", "precond.cli", "eval", "preconditions", "--cache", str(tmp_path / "cache")],
        capture_output=True, text=True, timeout=300, cwd=ROOT, env={**os.environ, "PRECOND_DATA_DIR": str(missing)},
    )
    assert result.returncode == 2, result.stderr
    assert str(missing / "sgd") in result.stderr and "PRECOND_DATA_DIR" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.stack
def test_serve_starts_its_own_redis_beside_an_open_one_and_prints_one_line_when_ready(
    tmp_path: Path, tiny_model_dir: Path
) -> None:
    """Beside a passwordless Redis on 6379 (Debian's redis-server: on this machine the system's own, else one
    started here), `precond serve` starts its own pair on free ports, names them in its ready line, and
    answers."""
    from precond.cli.supervisor import listening
    from precond.stack.local import RedisServer, free_port, make_stack

    squatter = None if listening("127.0.0.1", 6379) else RedisServer(tmp_path / "open", port=6379)
    if squatter is not None:
        (tmp_path / "open").mkdir()
        squatter.start()
    stack = make_stack(tmp_path, tiny_model_dir)
    stack.redis.stop()  # only its settings: no REDIS_URL, the private pair
    env = {k: v for k, v in stack.env.items() if k not in ("REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE")}
    port = free_port()
    process = subprocess.Popen([sys.executable, "-m", "precond.cli", "serve", "--port", str(port), "--data-dir",
                                str(tmp_path / "redis")], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True)
    guard = threading.Timer(240, process.terminate)  # a supervisor that never says so fails, not hangs
    guard.start()
    try:
        assert process.stdout is not None
        line = next((out for out in process.stdout if out.startswith("precond:")), "")  # not redis' or uvicorn's log
        ready = re.fullmatch(rf"precond: ready at http://127\.0\.0\.1:{port} \(GET /ready answers 200\), using its "
                             r"own password-protected Redis on 127\.0\.0\.1:(\d+) \(queue\) and :(\d+) \(cache\); "
                             r"no API keys: every caller is the tenant 'public', [\d.]+ requests/s \(bursts of \d+\), "
                             r"\d+ jobs at once \(--no-rate-limit lifts the rate\)\n", line)
        assert ready, line
        assert "6379" not in ready.groups()
        body = json.loads((EXAMPLES / "check-actions.json").read_text())
        answer = httpx.post(f"http://127.0.0.1:{port}/check-actions", params={"wait": 30}, timeout=60, json=body)
        assert answer.status_code == 200, answer.text
        body["history"] += "# " + "x" * 20_000 + "\n"  # large: read in the gateway's pool of processes
        assert httpx.post(f"http://127.0.0.1:{port}/check-actions", timeout=60, json=body).status_code == 200
        tree = _descendants(process.pid)
        assert any("spawn_main" in what for what in tree.values()), tree  # the gateway's check pool
        assert any("resource_tracker" in what for what in tree.values()), tree
        # a gateway that does not stop within the drain period is killed: what it started must go with it
        gateway = next(pid for pid, what in tree.items() if "uvicorn" in what)
        os.kill(gateway, signal.SIGSTOP)
        process.send_signal(signal.SIGTERM)
        assert process.wait(60) == 0
        left = [(pid, what) for pid, what in tree.items() if _alive(pid)]
        assert not left, f"left behind after SIGTERM: {left}"
    finally:
        guard.cancel()
        process.terminate()
        process.wait(60)
        if squatter is not None:
            squatter.stop()


@pytest.mark.stack
def test_what_serve_started_ends_with_it_even_when_it_is_killed(tmp_path: Path, tiny_model_dir: Path) -> None:
    """SIGKILL leaves no process a chance to stop what it started: a gateway killed so leaves no check process,
    and a `precond serve` killed so leaves no Redis, gateway, worker, check process or resource tracker."""
    from precond.stack.local import free_port, make_stack, wait_until

    stack = make_stack(tmp_path, tiny_model_dir)
    stack.redis.stop()
    env = {k: v for k, v in stack.env.items() if k not in ("REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE")}
    port = free_port()
    process = subprocess.Popen([sys.executable, "-m", "precond.cli", "serve", "--port", str(port), "--data-dir",
                                str(tmp_path / "redis")], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True)
    guard = threading.Timer(240, process.kill)
    guard.start()
    try:
        assert process.stdout is not None
        assert next((out for out in process.stdout if out.startswith("precond: ready")), "")
        body = json.loads((EXAMPLES / "check-actions.json").read_text())
        body["history"] += "# " + "x" * 20_000 + "\n"  # large: read in the gateway's pool of processes
        url = f"http://127.0.0.1:{port}/check-actions"
        assert httpx.post(url, timeout=60, json=body).status_code == 200
        tree = _descendants(process.pid)
        gateway = next(pid for pid, what in tree.items() if "uvicorn" in what)
        pool = _descendants(gateway)
        assert any("spawn_main" in what for what in pool.values()), pool
        os.kill(gateway, signal.SIGKILL)
        wait_until(lambda: not any(_alive(pid) for pid in pool), 15, "the killed gateway's check processes to end")
        wait_until(lambda: _answers(url, body), 60, "the restarted gateway")
        tree = _descendants(process.pid)
        assert any("redis-server" in what for what in tree.values()), tree
        process.kill()
        process.wait(10)
        wait_until(lambda: not any(_alive(pid) for pid in tree), 15, "what serve started to end")
    finally:
        guard.cancel()
        process.kill()
        process.wait(10)


def _answers(url: str, body: dict[str, object]) -> bool:
    try:
        return httpx.post(url, timeout=30, json=body).status_code == 200
    except httpx.HTTPError:
        return False


def _descendants(root: int) -> dict[int, str]:
    """Every process below `root`, with its command line."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    found: dict[int, str] = {}
    frontier = [root]
    while frontier:
        parent = frontier.pop()
        for pid, ppid in parents.items():
            if ppid == parent and pid not in found:
                try:
                    found[pid] = (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:200])
                except OSError:
                    continue
                frontier.append(pid)
    return found


def _alive(pid: int) -> bool:
    """Running, or stopped: not gone and not a zombie waiting for its parent."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_serve_refuses_a_named_redis_port_that_is_taken(redis_server: object) -> None:
    from precond.stack.local import RedisServer

    assert isinstance(redis_server, RedisServer)
    env = {k: v for k, v in os.environ.items() if k not in ("REDIS_URL", "PRECOND_REDIS_URL")}
    result = subprocess.run([sys.executable, "-m", "precond.cli", "serve", "--redis-port", str(redis_server.port)],
                            capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert result.returncode == 2, result.stderr
    assert f"--redis-port {redis_server.port}: port {redis_server.port} of 127.0.0.1" in result.stderr
    assert "Traceback" not in result.stderr and "--redis-url" not in result.stderr

"""The light client distribution (clients/python): its wheel holds `precond_client` (its schemas, the agent
adapters and the MCP proxy included) only and depends on httpx, pydantic and jsonschema only (the adapters'
frameworks and the MCP SDK are extras); installed alone in a fresh virtual environment (no system site packages), it
imports without torch, fastapi or redis and works against a real stack, its embedded guard included."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
import venv
import zipfile
from email.parser import Parser
from importlib.metadata import version
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from precond.stack.keyed import KeyedStack
from precond.stack.local import DEMOS, ROOT, SPEC


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Built from a copy of the two directories it needs (the build writes egg-info beside its sources)."""
    tree = tmp_path_factory.mktemp("light-src")
    shutil.copytree(ROOT / "clients" / "python", tree / "clients" / "python",
                    ignore=shutil.ignore_patterns("build", "*.egg-info"))
    shutil.copytree(ROOT / "precond_client", tree / "precond_client", ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("light-wheel")
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                           "-w", str(out), str(tree / "clients" / "python")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    [built] = out.glob("precond_client-*.whl")
    return built


def test_the_wheel_holds_the_client_and_its_schemas_and_needs_httpx_and_pydantic_only(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        [metadata] = [n for n in names if n.endswith(".dist-info/METADATA")]
        headers = Parser().parsestr(archive.read(metadata).decode())
    packages = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert packages == {"precond_client"}
    expected = {f"precond_client/{p.name}" for p in (ROOT / "precond_client").glob("*.py")}
    for package in ("schemas", "adapters", "mcp"):
        expected |= {f"precond_client/{package}/{p.name}" for p in (ROOT / "precond_client" / package).glob("*.py")}
    assert {n for n in names if n.endswith(".py")} == expected
    assert headers["Name"] == "precond-client"
    requires = sorted(headers.get_all("Requires-Dist") or [])
    base = [r for r in requires if "extra ==" not in r]
    assert [Requirement(r).name for r in base] == ["httpx", "jsonschema", "pydantic"], requires
    assert sorted(headers.get_all("Provides-Extra") or []) == ["langchain", "langgraph", "mcp", "openai-agents"]


def test_the_adapters_extras_are_bounded_by_the_versions_tested_and_the_docs_say_them() -> None:
    """Each adapter extra names its framework with the versions its tests ran with as bounds, the same in the
    service's test dependencies (which these tests install), and the installed versions are within them."""
    client = tomllib.loads((ROOT / "clients" / "python" / "pyproject.toml").read_text())
    service = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["dev"]
    guide = (ROOT / "docs" / "guard.md").read_text()
    for extra, requirements in client["project"]["optional-dependencies"].items():
        for text in requirements:
            requirement = Requirement(text)
            assert any(s.operator == "<" for s in requirement.specifier), f"{extra}: {text} has no upper bound"
            assert text in service, f"{text} is not among the service's test dependencies as it is in the extra"
            assert requirement.specifier.contains(version(requirement.name)), f"installed {requirement.name}"
            upper = next(s.version for s in requirement.specifier if s.operator == "<")
            assert f"<{upper}" in guide, f"docs/guard.md does not say {requirement.name}'s bound <{upper}"


USE = """
import json, sys
import precond_client
from precond_client import Client, History, rules
from precond_client.guard import Guard
from precond_client.openai_log import Tool, spec_program
args = json.loads(sys.argv[1])
with Client(args["url"], api_key=args["key"]) as client:
    made = client.create_set({"spec": args["spec"], "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]},
                              "demonstrations": args["demos"]})
    pinned = client.edit_set(made.id, [rules.require("SYSTEM.GOODBYE", "self.user.no_more")])
    history = History().user("INFORM_INTENT", "FindRestaurants").user("INFORM", "city'); import os; ('")
    verdict = client.check_with_set(pinned.reference, history, ["system.GOODBYE()"]).results[0]
    # the embedded guard: a set over a spec `precond convert openai` writes, judged here and by the service
    tools = [Tool("get_order", ("order_id",), frozenset({"order_id"})),
             Tool("cancel_order", ("order_id",), frozenset({"order_id"}))]
    orders = client.create_set({"spec": spec_program(tools, {"cancel_order"}),
                                "preconditions": {"AGENT.cancel_order": ["order_id in self.results['get_order']"]}})
    session = Guard.from_set(client.get_set(orders.reference)).session()
    messages = [{"role": "user", "content": "cancel 7"}]
    session.add(messages[0])
    cancel = {"name": "cancel_order", "arguments": '{"order_id": "7"}'}
    pairs = [(session.check(**cancel), client.check_with_set(orders.reference, messages, [cancel]).results[0])]
    read = [{"role": "assistant", "tool_calls": [{"function": {"name": "get_order",
                                                               "arguments": cancel["arguments"]}}]},
            {"role": "tool", "content": '{"status": "open"}'}]
    for message in read:
        session.add(message)
    messages += read
    pairs.append((session.check(**cancel), client.check_with_set(orders.reference, messages, [cancel]).results[0]))
heavy = sorted(m for m in ("torch", "transformers", "fastapi", "redis", "arq", "precond", "agents", "langgraph")
               if m in sys.modules)
print(json.dumps({"version": pinned.version, "allowed": verdict.allowed, "violations": verdict.violations,
                  "heavy": heavy, "file": precond_client.__file__,
                  "guard": [[e.model_dump() for e in pair] for pair in pairs]}))
"""


def test_installed_alone_it_works_against_a_real_stack(wheel: Path, keyed: KeyedStack, tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False).create(env_dir)
    python = env_dir / "bin" / "python"
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    installed = subprocess.run([str(python), "-m", "pip", "install", "-q", str(wheel)], capture_output=True,
                               text=True, timeout=300, check=False, env=clean)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    listed = subprocess.run([str(python), "-m", "pip", "list", "--format=json"], capture_output=True, text=True,
                            timeout=60, check=True, env=clean)
    present = {p["name"].lower() for p in json.loads(listed.stdout)}
    assert "precond-client" in present and not present & {"torch", "fastapi", "redis", "precondition-service"}
    args = json.dumps({"url": keyed.url, "key": keyed.keys["light"], "spec": SPEC, "demos": DEMOS})
    used = subprocess.run([str(python), "-I", "-c", USE, args], capture_output=True, text=True, timeout=120,
                          check=False, env=clean, cwd=tmp_path)
    assert used.returncode == 0, used.stdout + used.stderr
    answer = json.loads(used.stdout)
    assert answer["version"] == 2 and answer["heavy"] == []
    assert answer["file"].startswith(str(env_dir))  # the installed copy, not the checkout
    assert answer["allowed"] is False and answer["violations"] == ["self.user.no_more"]
    (before_embedded, before_service), (after_embedded, after_service) = answer["guard"]
    assert before_embedded == before_service and after_embedded == after_service
    assert before_embedded["violations"] == ["order_id in self.results['get_order']"] and after_embedded["allowed"]

"""The light client distribution (clients/python): its wheel holds `precond_client` (its schemas
included) only and
depends on httpx and pydantic only; installed alone in a fresh virtual environment (no system site packages),
it imports without torch, fastapi or redis and works against a real stack."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
import zipfile
from email.parser import Parser
from pathlib import Path

import pytest

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
    expected |= {f"precond_client/schemas/{p.name}" for p in (ROOT / "precond_client" / "schemas").glob("*.py")}
    assert {n for n in names if n.endswith(".py")} == expected
    assert headers["Name"] == "precond-client"
    requires = sorted(headers.get_all("Requires-Dist") or [])
    assert [r.split(">")[0].split("=")[0].strip() for r in requires] == ["httpx", "pydantic"], requires


USE = """
import json, sys
import precond_client
from precond_client import Client, History, rules
args = json.loads(sys.argv[1])
with Client(args["url"], api_key=args["key"]) as client:
    made = client.create_set({"spec": args["spec"], "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]},
                              "demonstrations": args["demos"]})
    pinned = client.edit_set(made.id, [rules.require("SYSTEM.GOODBYE", "self.user.no_more")])
    history = History().user("INFORM_INTENT", "FindRestaurants").user("INFORM", "city'); import os; ('")
    verdict = client.check_with_set(pinned.reference, history, ["system.GOODBYE()"]).results[0]
heavy = sorted(m for m in ("torch", "transformers", "fastapi", "redis", "arq", "precond")
               if m in sys.modules)
print(json.dumps({"version": pinned.version, "allowed": verdict.allowed, "violations": verdict.violations,
                  "heavy": heavy, "file": precond_client.__file__}))
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

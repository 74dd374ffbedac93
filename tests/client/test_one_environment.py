"""The service and the light client install into one fresh virtual environment beside another project's
top-level `schemas` module, and each imports its own: the project ships two top-level packages only
(`precond`, `precond_client`), the client distribution one, and neither takes a generic name from a user's
environment. Offline: wheels built from copies of the tree without build isolation, installed without
dependencies (the environment reads those from this one's site-packages)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

from precond.stack.local import ROOT

pytestmark = pytest.mark.stack

SQUATTER = """[build-system]
requires = ["setuptools>=77"]
build-backend = "setuptools.build_meta"

[project]
name = "another-project"
version = "1.0"

[tool.setuptools]
py-modules = ["schemas"]
"""


def build(source: Path, out: Path) -> Path:
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                           "-w", str(out), str(source)], capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    [built] = [w for w in out.glob("*.whl") if w.stat().st_mtime >= source.stat().st_mtime]
    return built


def copy_tree(tmp: Path, *paths: str) -> Path:
    """What a build reads, copied: a build writes `build/` and egg-info beside its sources."""
    tree = tmp / "tree"
    for path in paths:
        source = ROOT / path
        if source.is_dir():
            shutil.copytree(source, tree / path, ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
        else:
            (tree / path).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(source, tree / path)
    return tree


def test_service_and_client_install_beside_a_top_level_schemas_and_import_their_own(tmp_path: Path) -> None:
    squatter = tmp_path / "another"
    squatter.mkdir()
    (squatter / "pyproject.toml").write_text(SQUATTER)
    (squatter / "schemas.py").write_text("WHOSE = 'another project'\n")
    tree = copy_tree(tmp_path, "pyproject.toml", "README.md", "precond", "precond_client", "clients/python")
    wheels = [build(squatter, tmp_path / "w1"), build(tree / "clients" / "python", tmp_path / "w2"),
              build(tree, tmp_path / "w3")]

    env = tmp_path / "env"
    venv.EnvBuilder(with_pip=False, system_site_packages=False).create(env)
    python = env / "bin" / "python"
    installed = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
                                *map(str, wheels)], capture_output=True, text=True, timeout=300, check=False)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    (purelib / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")  # httpx, pydantic, ...

    top_level = sorted(p.name for p in purelib.iterdir() if p.suffix in ("", ".py") and not p.name.startswith("_"))
    assert top_level == ["precond", "precond_client", "schemas.py"], top_level
    code = ("import json, schemas, precond, precond_client, precond_client.schemas as api, "
            "precond.jobs.queue.keys as keys; "
            "print(json.dumps([schemas.WHOSE, precond.__file__, precond_client.__file__, api.__name__, keys.PREFIX]))")
    run = subprocess.run([str(python), "-I", "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path, check=False)
    assert run.returncode == 0, run.stderr
    whose, service, client, api_name, prefix = json.loads(run.stdout)
    assert whose == "another project" and api_name == "precond_client.schemas" and prefix == "precond"
    assert service.startswith(str(purelib)) and client.startswith(str(purelib))

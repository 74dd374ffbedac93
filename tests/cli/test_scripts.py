"""scripts/serve.sh and scripts/install.sh as a user runs them: no surprise at a restart, no false ready line."""

from __future__ import annotations

import shutil
import stat
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

FAKE_PYTHON = """#!/usr/bin/env bash
echo "$*" >> "$(dirname "$0")/../calls.log"
"""


def _checkout(tmp_path: Path) -> Path:
    """A copy of what install.sh reads, with a .venv whose python only records how it was called."""
    (tmp_path / "scripts").mkdir()
    shutil.copy2(ROOT / "scripts" / "install.sh", tmp_path / "scripts" / "install.sh")
    shutil.copy2(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "python").write_text(FAKE_PYTHON)
    (bin_dir / "python").chmod(stat.S_IRWXU)
    (bin_dir / "activate").write_text(f'PATH="{bin_dir}:$PATH"\n')
    return tmp_path


def _install(checkout: Path, **env: str) -> subprocess.CompletedProcess[str]:
    """Only the fake .venv's python is on PATH: the script can reach no real pip (and so no real virtualenv)."""
    bin_dir = checkout / ".venv" / "bin"
    path = f"{bin_dir}:/usr/bin:/bin:/usr/sbin:/sbin"
    assert shutil.which("python", path=path) == str(bin_dir / "python")
    environment = {"PATH": path, "HOME": str(checkout), "PRECOND_INSTALL_REDIS": "0", **env}
    return subprocess.run(["bash", "scripts/install.sh"], cwd=checkout, env=environment, capture_output=True,
                          text=True, timeout=60)


def _pip_calls(checkout: Path) -> list[str]:
    log = checkout / ".venv" / "calls.log"
    return log.read_text().splitlines() if log.exists() else []


def test_install_runs_pip_only_when_something_changed(tmp_path: Path) -> None:
    checkout = _checkout(tmp_path)
    assert _install(checkout).returncode == 0
    first = _pip_calls(checkout)
    assert any("torch==" in call for call in first) and any("-e .[" in call for call in first)
    again = _install(checkout)
    assert again.returncode == 0 and _pip_calls(checkout) == first, "an unchanged checkout installs nothing"
    assert "pip skipped" in again.stderr
    assert _install(checkout, PRECOND_EXTRAS="model").returncode == 0
    assert len(_pip_calls(checkout)) > len(first), "other extras: installed again"
    count = len(_pip_calls(checkout))
    with (checkout / "pyproject.toml").open("a") as pyproject:
        pyproject.write("\n# a new dependency\n")
    assert _install(checkout, PRECOND_EXTRAS="model").returncode == 0
    assert len(_pip_calls(checkout)) > count, "a changed pyproject.toml: installed again"


def test_serve_sh_never_prints_the_ready_line_itself() -> None:
    """`grep 'precond: ready at'` on serve.sh's output must match only the supervisor's line, printed when
    GET /ready answers 200 (tests/cli/test_cli.py checks that one)."""
    assert "precond: ready" not in (ROOT / "scripts" / "serve.sh").read_text()

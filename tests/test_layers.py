"""Data flows one way, gateway → queue → worker → engine → sandbox: each package's imports, read from its AST.

The gateway (`service/`) and the queue worker (`worker/`) speak the job protocol (`jobs/`) and never import
each other; the engine knows nothing of queues or HTTP; the sandbox and the spec reader (`programs/`) stand
alone, and `programs/` (imported by the sandbox's stdlib-only child) uses the standard library only.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = ("schemas", "jobs", "engine", "programs", "sandbox", "service", "worker", "cli", "evaluation", "stack",
           "precond_client", "convert")

FORBIDDEN: dict[str, set[str]] = {
    "service": {"worker", "engine", "cli", "evaluation", "stack"},
    "worker": {"service", "cli", "evaluation", "stack"},
    "engine": {"worker", "jobs", "service", "cli", "evaluation", "stack"},
    "jobs": {"service", "worker", "cli", "evaluation", "stack"},
    "sandbox": set(PROJECT) - {"sandbox", "programs"},
    "programs": set(PROJECT) - {"programs"},
    "schemas": set(PROJECT) - {"schemas"},
    "precond_client": set(PROJECT) - {"precond_client", "schemas"},  # light: installable without the service
    "convert": set(PROJECT) - {"convert", "programs", "schemas"},
}


def imports(package: str) -> list[tuple[str, str]]:
    """(file, absolute module name) of every import in the package; relative imports stay in the package."""
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found += [(str(path.relative_to(ROOT)), alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                module = package if node.level else (node.module or "")  # relative: inside the package
                found.append((str(path.relative_to(ROOT)), module))
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_only_what_its_layer_allows(package: str) -> None:
    wrong = [
        f"{file}: {module}" for file, module in imports(package)
        if module.split(".")[0] in FORBIDDEN[package]
    ]
    assert not wrong, f"{package}/ must not import these (see README, How it fits together):\n" + "\n".join(wrong)


def test_programs_is_stdlib_only() -> None:
    outside = [
        f"{file}: {module}" for file, module in imports("programs")
        if module.split(".")[0] not in {*sys.stdlib_module_names, "programs", "__future__"}
    ]
    assert not outside, outside


def test_the_checker_sees_imports() -> None:
    # a guard against a walker that finds nothing and so passes everything
    assert ("worker/runner.py", "jobs.heartbeats") in imports("worker")
    assert any(module.startswith("engine.") for _, module in imports("worker"))


@pytest.mark.parametrize("directory", ["stack", "bench"])
def test_test_support_and_benchmarks_never_import_tests(directory: str) -> None:
    wrong = [f"{file}: {module}" for file, module in imports(directory) if module.split(".")[0] == "tests"]
    assert not wrong, f"{directory}/ must not import tests/ (shared helpers belong in stack/):\n" + "\n".join(wrong)


def test_the_sandbox_child_is_stdlib_only_and_apart_from_the_worker_side() -> None:
    """It runs under `python -I -S` with a bare `sandbox` package: no site-packages, no `sandbox/__init__`."""
    outside = [
        f"{file}: {module}" for file, module in imports("sandbox/child")
        if module.split(".")[0] not in {*sys.stdlib_module_names, "programs", "__future__", "sandbox/child"}
    ]
    assert not outside, outside


def loaded_by(statement: str) -> set[str]:
    """Top-level packages a fresh interpreter has loaded after `statement` (what an import drags in, not only
    what the files name)."""
    code = f"import sys\n{statement}\nprint(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                            check=True)
    return set(result.stdout.split())


@pytest.mark.parametrize(("statement", "never"), [
    ("from service.app import create_app; create_app", {"sandbox", "engine", "worker", "torch", "transformers"}),
    ("import jobs.keys, jobs.records, jobs.heartbeats, jobs.cache", {"sandbox", "engine", "service", "worker",
                                                                     "torch"}),
    ("import worker.runner", {"service", "cli", "torch", "transformers"}),
])
def test_importing_a_layer_loads_nothing_below_or_above_it(statement: str, never: set[str]) -> None:
    """The gateway computes job ids and checks programs without the engine or the sandbox, and the worker loads
    the model code only when it builds a model, never at import."""
    assert not loaded_by(statement) & never

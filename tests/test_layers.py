"""Data flows one way, gateway → queue → worker → engine → sandbox: each package's imports, read from its AST.

The gateway (`precond.gateway`) and the queue worker (`precond.worker`) speak the job protocol (`precond.jobs`)
and never import each other; the engine knows nothing of queues or HTTP; the sandbox and the spec reader
(`precond.programs`) stand alone, and `precond.programs` (imported by the sandbox's stdlib-only child) uses the
standard library only. The client (`precond_client`) imports no service layer; the reading of an OpenAI agent's
messages (`precond_client.openai_log`), which the converter and the client's embedded guard share, and the guard's
rule interpreter (`precond_client.rule_interpreter`, with what it charges: `precond_client.rule_work`) use the
standard library only and import nothing else of the project but their one parse (`precond_client.parsing`).
Layers are named by their module path below the distribution's packages.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {f"precond.{name}" for name in ("jobs", "store", "patches", "engine", "programs", "sandbox", "gateway",
                                        "worker", "cli", "evaluation", "stack", "convert")}
LAYERS |= {"precond.engine.candidates", "precond.engine.judging", "precond.engine.acting"}  # the engine's rooms
SCHEMAS = "precond_client.schemas"
OPENAI_LOG = "precond_client.openai_log"
INTERPRETER = "precond_client.rule_interpreter"
WORK = "precond_client.rule_work"
PARSING = "precond_client.parsing"
CLIENT = "precond_client"
STANDALONE = (OPENAI_LOG, INTERPRETER, WORK, PARSING)
"""Standard library only, nothing else of the project: shared by the service and the light client."""
PROJECT = (*sorted(LAYERS), SCHEMAS, *STANDALONE, CLIENT)


def p(*names: str) -> set[str]:
    return {f"precond.{name}" for name in names}


FORBIDDEN: dict[str, set[str]] = {
    "precond.engine.candidates": p("engine.judging", "engine.acting"),  # generating never asks the judges
    "precond.engine.judging": p("engine.acting"),
    "precond.gateway": p("worker", "engine", "cli", "evaluation", "stack"),
    "precond.worker": p("gateway", "cli", "evaluation", "stack"),
    "precond.engine": p("worker", "jobs", "store", "gateway", "cli", "evaluation", "stack"),
    "precond.jobs": p("store", "gateway", "worker", "cli", "evaluation", "stack"),
    "precond.store": p("gateway", "worker", "engine", "sandbox", "cli", "evaluation", "stack"),
    "precond.patches": set(PROJECT) - p("patches"),
    "precond.sandbox": set(PROJECT) - p("sandbox", "programs"),
    "precond.programs": set(PROJECT) - p("programs"),
    SCHEMAS: set(PROJECT) - {SCHEMAS},
    OPENAI_LOG: set(PROJECT) - {OPENAI_LOG, PARSING},
    INTERPRETER: set(PROJECT) - {INTERPRETER, WORK, PARSING},
    WORK: set(PROJECT) - {WORK},
    PARSING: set(PROJECT) - {PARSING},
    CLIENT: LAYERS,  # light: installable without the service (its own schemas included)
    "precond.convert": set(PROJECT) - {*p("convert", "programs"), SCHEMAS, OPENAI_LOG},
}


def layer_of(module: str) -> str | None:
    """The project layer a module belongs to (the longest layer name it starts with), or None outside it."""
    found = [layer for layer in PROJECT if module == layer or module.startswith(layer + ".")]
    return max(found, key=len) if found else None


def directory(package: str) -> Path:
    return ROOT.joinpath(*package.split("."))


def sources(layer: str) -> list[Path]:
    """The files of a package, or the one file of a module."""
    folder = directory(layer)
    return sorted(folder.rglob("*.py")) if folder.is_dir() else [folder.with_suffix(".py")]


def imports(package: str) -> list[tuple[str, str]]:
    """(file, absolute module name) of every import in the package; relative imports stay in the package."""
    found = []
    for path in sources(package):
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
        if layer_of(module) in FORBIDDEN[package]
    ]
    assert not wrong, f"{package} must not import these (see docs/architecture.md):\n" + "\n".join(wrong)


@pytest.mark.parametrize("layer", ["precond.programs", *STANDALONE])
def test_shared_readers_are_stdlib_only(layer: str) -> None:
    found = imports(layer)
    outside = [
        f"{file}: {module}" for file, module in found
        if module.split(".")[0] not in {*sys.stdlib_module_names, "__future__"} and layer_of(module) != layer
        and not (layer == INTERPRETER and layer_of(module) == WORK) and layer_of(module) != PARSING
    ]
    assert found and not outside, outside


def test_the_checker_sees_imports() -> None:
    # a guard against a walker that finds nothing and so passes everything
    assert ("precond/worker/runner.py", "precond.jobs.queue.heartbeats") in imports("precond.worker")
    assert any(module.startswith("precond.engine.") for _, module in imports("precond.worker"))
    assert layer_of("precond_client.schemas") == SCHEMAS and layer_of("precond_client.aio") == CLIENT
    assert ("precond/convert/openai.py", OPENAI_LOG) in imports("precond.convert")
    assert ("precond_client/guard.py", INTERPRETER) in imports(CLIENT)


@pytest.mark.parametrize("package", ["precond.stack", "bench"])
def test_test_support_and_benchmarks_never_import_tests(package: str) -> None:
    wrong = [f"{file}: {module}" for file, module in imports(package) if module.split(".")[0] == "tests"]
    assert not wrong, f"{package} must not import tests/ (shared helpers belong in precond.stack):\n" + "\n".join(wrong)


def test_the_sandbox_child_is_stdlib_only_and_apart_from_the_worker_side() -> None:
    """It runs under `python -I -S` with bare `precond` and `precond.sandbox` packages: no site-packages, no
    `precond/sandbox/__init__.py`."""
    outside = [
        f"{file}: {module}" for file, module in imports("precond.sandbox.child")
        if module.split(".")[0] not in {*sys.stdlib_module_names, "__future__"}
        and layer_of(module) != "precond.programs" and module != "precond.sandbox.child"
        and not module.startswith("precond.sandbox.child.")
    ]
    assert not outside, outside


def loaded_by(statement: str) -> set[str]:
    """Modules, top-level packages and project layers a fresh interpreter has loaded after `statement` (what an
    import drags in, not only what the files name)."""
    code = f"import sys\n{statement}\nprint(' '.join(sorted(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                            check=True)
    modules = result.stdout.split()
    return {*modules, *(m.split(".")[0] for m in modules), *(layer for m in modules if (layer := layer_of(m)))}


@pytest.mark.parametrize(("statement", "never"), [
    ("from precond.gateway.app import create_app; create_app",
     {*p("sandbox", "engine", "worker"), "torch", "transformers"}),
    ("import precond.jobs.queue.keys, precond.jobs.records, precond.jobs.queue.heartbeats, precond.jobs.cache",
     {*p("sandbox", "engine", "gateway", "worker"), "torch"}),
    ("import precond.worker.runner", {*p("gateway", "cli"), "torch", "transformers"}),
    ("import precond_client.schemas", {*LAYERS, "precond_client.aio", "precond_client.sync", "httpx"}),
    ("import precond_client.guard", {*LAYERS, "httpx", "agents", "langgraph", "langchain_core"}),
])
def test_importing_a_layer_loads_nothing_below_or_above_it(statement: str, never: set[str]) -> None:
    """The gateway computes job ids and checks programs without the engine or the sandbox, the worker loads
    the model code only when it builds a model, never at import, and the service reads the wire contract
    (`precond_client.schemas`) without the client's transport; the embedded guard needs neither the network
    nor an agent framework."""
    assert not loaded_by(statement) & never

"""The image starts: exactly what the Dockerfile copies is enough to import every entry point its containers run.

The compose file's other tests read its YAML; this one rebuilds the image's /app from the Dockerfile's COPY lines
into an empty directory and imports from there alone (no project package from anywhere else), because a module
the Dockerfile forgets fails only when a container starts: `keys`, the gateway and the workers all import
`precond.cli`.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]

ENTRY_POINTS = (
    "precond.cli.main",  # `precond serve|worker|keys` (CMD, compose's keys and workers)
    "precond.gateway.app",  # the gateway (uvicorn precond.gateway.app:create_app)
    "precond.cli.supervisor",  # `precond serve` imports it when it starts
    "precond.worker.runner",  # `precond worker`
    "precond.worker.training_process",  # a worker's policy training (`python -m`)
    "precond.engine.factory",  # `precond infer|check` in-process
    "precond_client",  # `precond infer --server URL`
)

ISOLATED_IMPORT = """
import importlib, sys
PROJECT = {"precond", "precond_client"}
# Only the copied /app: drop the development checkout's editable-install finder and any path into it.
sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable__")]
sys.path[:] = [sys.argv[1]] + [p for p in sys.path if "site-packages" in p or "lib/python" in p]
for name in sys.argv[2:]:
    module = importlib.import_module(name)
    assert module.__file__.startswith(sys.argv[1]), (name, module.__file__)
outside = [m.__name__ for m in list(sys.modules.values())
           if m.__name__.split(".")[0] in PROJECT and not (m.__file__ or "").startswith(sys.argv[1])]
assert not outside, outside
print("ok")
"""


def copied_paths(dockerfile: str) -> list[str]:
    """The sources of every `COPY` into the build stage (not `--from` another stage), as written."""
    paths: list[str] = []
    for line in re.findall(r"^COPY (?!--from)(.+)$", dockerfile, flags=re.MULTILINE):
        *sources, _ = line.split()
        paths += [s for s in sources if not s.startswith("--")]
    return paths


def build_app_dir(target: Path) -> None:
    for source in copied_paths((ROOT / "Dockerfile").read_text()):
        for path in ROOT.glob(source):
            dest = target / path.relative_to(ROOT)
            if path.is_dir():
                shutil.copytree(path, dest, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(path, dest)


def test_copy_lines_are_read() -> None:
    # a guard against a parser that finds nothing and so imports from nowhere
    assert {"precond", "precond_client", "scripts/install.sh"} <= set(copied_paths((ROOT / "Dockerfile").read_text()))


def test_every_entry_point_imports_from_what_the_dockerfile_copies(tmp_path: Path) -> None:
    app = tmp_path / "app"
    build_app_dir(app)
    out = subprocess.run([sys.executable, "-I", "-c", ISOLATED_IMPORT, str(app), *ENTRY_POINTS], cwd=app,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]


def test_a_module_the_dockerfile_forgets_is_caught(tmp_path: Path) -> None:
    app = tmp_path / "app"
    build_app_dir(app)
    shutil.rmtree(app / "precond" / "convert")
    out = subprocess.run([sys.executable, "-I", "-c", ISOLATED_IMPORT, str(app), "precond.cli.main"], cwd=app,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and "No module named 'precond.convert'" in out.stderr


def _compose_client() -> list[str] | None:
    """`docker compose` (v2 plugin) or `docker-compose`, if either works here; neither needs an engine for
    `config`."""
    for command in (["docker", "compose"], ["docker-compose"]):
        if shutil.which(command[0]) is None:
            continue
        probe = subprocess.run([*command, "version"], capture_output=True, text=True)
        if probe.returncode == 0:
            return command
    return None


@pytest.mark.parametrize("profile", [None, "gpu"])
def test_compose_config_is_accepted_by_a_compose_client(profile: str | None) -> None:
    client = _compose_client()
    if client is None:
        pytest.skip("no compose client here (`docker compose` and `docker-compose` both missing)")
    profiles = ["--profile", profile] if profile else []
    out = subprocess.run([*client, "-f", str(ROOT / "docker-compose.yml"), *profiles, "config"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    config = yaml.safe_load(out.stdout)
    assert {"keys", "redis", "redis-cache", "gateway", "worker"} <= set(config["services"])
    if profile == "gpu":  # torch from PyPI (TORCH_INDEX empty): its 2.13.0 wheel is the CUDA build
        assert config["services"]["worker-gpu"]["build"]["args"]["TORCH_INDEX"] == ""

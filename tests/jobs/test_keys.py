"""The job id's model part: the gateway reads the same `MODEL_*` variables the workers load the model with."""

from __future__ import annotations

import json
import os

import pytest

from precond.engine.settings import ModelSettings
from precond.jobs.queue import keys
from precond_client.schemas import JobKind


def test_the_gateway_reads_the_variables_the_model_settings_read() -> None:
    assert ModelSettings.model_config.get("env_prefix") == keys.MODEL_ENV_PREFIX
    assert ModelSettings.model_config.get("env_file") is None  # the environment is the only source


def test_a_model_setting_changes_the_identity_and_other_variables_do_not(monkeypatch: pytest.MonkeyPatch) -> None:
    identity = keys.model_identity.__wrapped__
    for name in [n for n in os.environ if n.upper().startswith("MODEL_")]:
        monkeypatch.delenv(name)
    bare = identity()
    monkeypatch.setenv("PRECOND_SOMETHING", "1")
    assert identity() == bare
    monkeypatch.setenv("model_path", "/models/other")  # read case-insensitively, like pydantic-settings
    changed = json.loads(identity())
    assert changed[1] == [["MODEL_PATH", "/models/other"]]
    assert ModelSettings().path == "/models/other"


@pytest.mark.parametrize("kind", ["infer", "next-action", "check", "validate", "reinfer", "train-policy"])
def test_a_job_id_is_read_once_into_its_kind_and_tenant(kind: JobKind) -> None:
    tag = keys.tenant_tag(b"secret", "acme")
    job = keys.JobId.parse(keys.job_id(kind, {"n": 1}, None, b"secret", tag))
    assert (job.kind, job.tenant) == (kind, tag) and str(job) == job.value


@pytest.mark.parametrize("bad", [
    "", "check", "check--" + "0" * 48, "check-" + "0" * 48,  # no tenant: an error, never "" or the id itself
    "check-" + "a" * 15 + "-" + "0" * 48, "nope-" + "a" * 16 + "-" + "0" * 48, "check-" + "A" * 16 + "-" + "0" * 48,
])
def test_an_id_without_a_tenant_or_of_another_shape_is_no_job(bad: str) -> None:
    with pytest.raises(keys.NotAJobId):
        keys.JobId.parse(bad)
    assert keys.JobId.read(bad) is None

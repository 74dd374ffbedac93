"""deploy/kubernetes/ offline: every rendered resource is valid for the Kubernetes API (kubernetes-validate's
bundled schemas, strict) and KEDA's CRDs (tests/fixtures/kubernetes/); the overlays' patches apply; the
manifests run what the image runs, scale on the queues the code uses, lock every container down and let
nothing reach the workers or the Redis servers but the service itself."""

from __future__ import annotations

import copy
import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import pytest
import yaml
from kustomize_render import PatchError, Resource, apply_patch, load_documents, pod_specs, render
from manifests import KUBERNETES, ROOT, TARGETS, base, container, named, pod_spec
from network_policy import Pod, can_connect

from precond.cli.main import app as cli_app
from precond.gateway.routes import health
from precond.gateway.server import gateway_args
from precond.jobs.queue.keys import MODEL_QUEUE, QUEUES, TRAIN_QUEUE
from precond.jobs.redis_roles import acl_file, password_file
from precond.worker.settings import WorkerSettings, queue_names

KUBERNETES_VERSION = "1.32.0"
"""The oldest Kubernetes these manifests are checked against (autoscaling/v2, policy/v1 and
networking.k8s.io/v1 are all stable there)."""
FIXTURES = ROOT / "tests" / "fixtures" / "kubernetes"
CRD_SCHEMAS = {
    ("keda.sh/v1alpha1", "ScaledObject"): "keda-scaledobject-v1alpha1.json",
    ("keda.sh/v1alpha1", "TriggerAuthentication"): "keda-triggerauthentication-v1alpha1.json",
}
NAMESPACE = "precond"
IMAGE_USER = 10001
WORKERS = ("precond-worker", "precond-trainer")
"""The serving workers (every queue but the training one) and the training workers."""


def target_id(path: Path) -> str:
    return str(path.relative_to(KUBERNETES))


@pytest.fixture(scope="module", params=TARGETS, ids=target_id)
def rendered(request: pytest.FixtureRequest) -> list[Resource]:
    return render(request.param)


def strict(schema: Any) -> Any:
    """A CRD's structural schema as the API server's strict field validation reads it: no field it does not
    declare (unless it says x-kubernetes-preserve-unknown-fields)."""
    if isinstance(schema, dict):
        schema = {key: strict(value) for key, value in schema.items()}
        if ("properties" in schema and "additionalProperties" not in schema
                and not schema.get("x-kubernetes-preserve-unknown-fields")):
            schema["additionalProperties"] = False
        return schema
    if isinstance(schema, list):
        return [strict(item) for item in schema]
    return schema


def validate(resource: Resource) -> None:
    crd = CRD_SCHEMAS.get((resource["apiVersion"], resource["kind"]))
    if crd is None:
        kubernetes_validate.validate(resource, KUBERNETES_VERSION, strict=True)
        return
    schema = strict(json.loads((FIXTURES / crd).read_text()))
    jsonschema.Draft7Validator(schema).validate(resource)


# ---- valid everywhere -----------------------------------------------------------------------------------


def test_every_file_is_in_a_kustomization() -> None:
    listed = {(directory / entry).resolve() for directory in TARGETS
              for entry in yaml.safe_load((directory / "kustomization.yaml").read_text()).get("resources", [])}
    files = {path.resolve() for path in KUBERNETES.rglob("*.yaml") if path.name != "kustomization.yaml"}
    assert files and files <= listed, files - listed


def test_every_resource_is_valid_for_the_kubernetes_api_and_kedas_crds(rendered: list[Resource]) -> None:
    kinds = {r["kind"] for r in rendered}
    assert {"Deployment", "StatefulSet", "HorizontalPodAutoscaler", "ScaledObject", "TriggerAuthentication",
            "NetworkPolicy", "PodDisruptionBudget", "Service", "ConfigMap", "Namespace"} <= kinds
    for resource in rendered:
        validate(resource)


@pytest.mark.parametrize(("kind", "path", "value"), [
    ("Deployment", ["spec", "template", "spec", "containers", 0, "readOnlyRootFileSystem"], True),
    ("ScaledObject", ["spec", "minReplicas"], 1),
    ("ScaledObject", ["spec", "triggers", 0, "authRef"], {"name": "precond-redis"}),
    ("NetworkPolicy", ["spec", "ingres"], []),
])
def test_the_validation_refuses_a_misspelt_field(kind: str, path: list[Any], value: Any) -> None:
    resource = copy.deepcopy(next(r for r in base() if r["kind"] == kind))
    node: Any = resource
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    with pytest.raises((kubernetes_validate.ValidationError, jsonschema.ValidationError)):
        validate(resource)


def test_overlays_patch_what_they_name() -> None:
    dev, production = (render(KUBERNETES / "overlays" / name) for name in ("dev", "production"))
    assert named(dev, "HorizontalPodAutoscaler", "precond-gateway")["spec"]["maxReplicas"] == 2
    assert named(dev, "ScaledObject", "precond-worker")["spec"]["maxReplicaCount"] == 2
    assert container(dev, "Deployment", "precond-worker")["image"] == "precondition-service:dev"
    image = container(production, "Deployment", "precond-gateway")["image"]
    assert re.fullmatch(r"\S+/precondition-service:\d+\.\d+\.\d+", image)
    for name in ("precond-gateway", "precond-worker"):
        assert pod_spec(production, "Deployment", name)["topologySpreadConstraints"]
    with pytest.raises(PatchError):  # a patch on a resource that is not there fails, as in kustomize
        apply_patch(base(), {"target": {"kind": "Deployment", "name": "precond-gatway"},
                             "patch": "- {op: replace, path: /spec/replicas, value: 1}"})
    with pytest.raises(PatchError):
        apply_patch(base(), {"target": {"kind": "ScaledObject", "name": "precond-worker"},
                             "patch": "- {op: replace, path: /spec/maxReplicas, value: 1}"})


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="no kubectl here: the Python rendering stands alone")
@pytest.mark.parametrize("directory", TARGETS, ids=target_id)
def test_the_python_rendering_is_what_kubectl_kustomize_prints(directory: Path) -> None:
    out = subprocess.run(["kubectl", "kustomize", str(directory)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert [doc for doc in yaml.safe_load_all(out.stdout) if doc] == render(directory)


def test_no_secret_is_kept_in_the_manifests() -> None:
    for path in KUBERNETES.rglob("*.yaml"):
        assert all(doc.get("kind") != "Secret" for doc in load_documents(path)), path
        assert "secretGenerator" not in path.read_text(), path


# ---- the image's entry points ---------------------------------------------------------------------------


def compose() -> dict[str, Any]:
    return dict(yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"])


def test_the_gateway_runs_as_every_other_start_does(rendered: list[Resource]) -> None:
    gateway = container(rendered, "Deployment", "precond-gateway")
    assert gateway["command"] == ["uvicorn", *gateway_args(1), "--host", "0.0.0.0", "--port", "8000"]
    assert gateway["command"] == compose()["gateway"]["command"][:-2]  # compose's, less its --workers option
    assert gateway["ports"] == [{"name": "http", "containerPort": 8000}]
    assert "http://127.0.0.1:8000/health" in (ROOT / "docker" / "healthcheck.py").read_text()
    routes = {route.path for route in health.router.routes}  # type: ignore[attr-defined]
    assert {gateway["livenessProbe"]["httpGet"]["path"], gateway["readinessProbe"]["httpGet"]["path"]} == {
        "/health", "/ready"} <= routes


@pytest.mark.parametrize(("deployment", "service"), [("precond-worker", "worker"), ("precond-trainer", "trainer")])
def test_the_worker_runs_as_compose_does_and_its_probes_are_the_images(rendered: list[Resource], deployment: str,
                                                                        service: str) -> None:
    worker = container(rendered, "Deployment", deployment)
    assert worker["command"] == compose()[service]["command"] == ["precond", "worker"]
    assert env_of(worker)["PRECOND_WORKER_QUEUES"] == compose()[service]["environment"]["PRECOND_WORKER_QUEUES"]
    assert "worker" in {command.name or command.callback.__name__ for command in cli_app.registered_commands}
    assert re.search(r"^COPY docker docker$", (ROOT / "Dockerfile").read_text(), flags=re.MULTILINE)
    healthcheck = (ROOT / "docker" / "healthcheck.py").read_text()
    modes = set(re.findall(r'"([a-z-]+)": [a-z_]+[,}]', healthcheck))
    for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
        python, script, mode = worker[probe]["exec"]["command"]
        assert (python, script) == ("python", "docker/healthcheck.py") and mode in modes, probe
    assert worker["readinessProbe"]["exec"]["command"][-1] == "worker-ready"


def test_the_pods_run_as_the_images_user() -> None:
    uid = re.search(r"useradd .*--uid (\d+) precond", (ROOT / "Dockerfile").read_text())
    assert uid and int(uid.group(1)) == IMAGE_USER
    for name in ("precond-gateway", *WORKERS):
        assert pod_spec(base(), "Deployment", name)["securityContext"]["runAsUser"] == IMAGE_USER


OWN_REDIS = {"REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE", "PRECOND_CACHE_REDIS_URL", "PRECOND_CACHE_REDIS_PASSWORD_FILE"}
"""The settings by which gateways and workers each reach each Redis as their own user (precond/jobs/redis_roles.py)."""
ROLE_OF = {"precond-gateway": ("gateway", "gateway"), "precond-worker": ("worker", "worker"),
           "precond-trainer": ("worker", "trainer")}
"""Deployment → (its Redis users' role, its compose service)."""


def test_gateways_and_workers_read_one_environment(rendered: list[Resource]) -> None:
    """MODEL_* settings are part of every cache key: both sides read them from one ConfigMap, as compose
    gives both one environment block, and a container sets none of its own. Each reaches each Redis as its own
    user, as in compose."""
    config = named(rendered, "ConfigMap", "precond-config")["data"]
    services = compose()
    for name, (role, service) in ROLE_OF.items():
        spec = container(rendered, "Deployment", name)
        assert spec["envFrom"] == [{"configMapRef": {"name": "precond-config"}}]
        assert not [e for e in spec.get("env", []) if e["name"].upper().startswith("MODEL_")]
        own, composed = env_of(spec), services[service]["environment"]
        assert own["REDIS_URL"] == f"redis://{role}@precond-redis:6379/0", name
        assert own["PRECOND_CACHE_REDIS_URL"] == f"redis://{role}@precond-redis-cache:6379/0", name
        for variable in ("PRECOND_REDIS_PASSWORD_FILE", "PRECOND_CACHE_REDIS_PASSWORD_FILE"):
            assert own[variable] == composed[variable], name  # the same role's file as in compose
    assert not OWN_REDIS & set(config)
    compose_env = {k: v for k, v in services["gateway"]["environment"].items() if k not in OWN_REDIS}
    assert set(compose_env) <= set(config)
    for name, value in compose_env.items():
        assert config[name] == value, name
    for service in ("precond-redis", "precond-redis-cache"):
        named(rendered, "Service", service)


# ---- scaling ----------------------------------------------------------------------------------------------


def env_of(spec: dict[str, Any]) -> dict[str, str]:
    return {e["name"]: e["value"] for e in spec.get("env", [])}


def test_workers_scale_on_exactly_the_queues_they_read(rendered: list[Resource]) -> None:
    """Serving and training workers split the queues the code uses, and each scales on the ones it reads."""
    read = {name: queue_names(env_of(container(rendered, "Deployment", name))["PRECOND_WORKER_QUEUES"])
            for name in WORKERS}
    assert read["precond-trainer"] == [TRAIN_QUEUE] and sorted(read["precond-worker"] + [TRAIN_QUEUE]) == sorted(QUEUES)
    for name in WORKERS:
        scaled = named(rendered, "ScaledObject", name)
        assert scaled["spec"]["scaleTargetRef"]["name"] == name
        triggers = scaled["spec"]["triggers"]
        assert {t["type"] for t in triggers} == {"redis"}
        assert sorted(t["metadata"]["listName"] for t in triggers) == sorted(read[name])
        assert "replicas" not in named(rendered, "Deployment", name)["spec"], "KEDA owns it"
    scaled = named(rendered, "ScaledObject", "precond-worker")
    assert scaled["spec"]["minReplicaCount"] >= 1, "the gateways' /ready needs a serving worker"
    namespace = scaled["metadata"]["namespace"]
    for trigger in [t for name in WORKERS for t in named(rendered, "ScaledObject", name)["spec"]["triggers"]]:
        # KEDA's operator resolves the address from its own namespace: it must name the Service's
        assert trigger["metadata"]["address"] == f"precond-redis.{namespace}.svc:6379"
        assert int(trigger["metadata"]["listLength"]) >= 1
        auth = named(rendered, "TriggerAuthentication", trigger["authenticationRef"]["name"])
        assert auth["spec"]["secretTargetRef"] == [  # the queue Redis's read-only `keda` user
            {"parameter": "username", "name": "precond-secrets", "key": "redis-queue-keda-username"},
            {"parameter": "password", "name": "precond-secrets", "key": password_file("queue", "keda")}]


MIB = 1024 * 1024
SERVING_PEAK_BYTES = 1_020_000_000
"""A serving worker's peak with the embedded model in int8 over an inference (docs/model-speed.md)."""


def quantity(value: str) -> int:
    """Bytes of a Kubernetes or compose memory quantity (`1280Mi`, `5Gi`, `5G`, `1280M`)."""
    number, unit = re.fullmatch(r"(\d+)([KMG]i?)", value).groups()  # type: ignore[union-attr]
    return int(number) * {"K": 10**3, "M": 10**6, "G": 10**9, "Ki": 2**10, "Mi": 2**20, "Gi": 2**30}[unit]


def test_serving_workers_stay_small_and_training_workers_hold_a_training(rendered: list[Resource]) -> None:
    """A serving worker never trains, so its limit is the model's serving peak and the growth its job bound lets
    a job add (at most ~1.3 GB); a training worker's limit holds a training's process up to its own bound."""
    serving = container(rendered, "Deployment", "precond-worker")
    limit = quantity(serving["resources"]["limits"]["memory"])
    job_bound = int(env_of(serving)["PRECOND_JOB_MAX_MEMORY_MB"]) * MIB
    assert SERVING_PEAK_BYTES + job_bound <= limit
    trainer = container(rendered, "Deployment", "precond-trainer")
    training_bound = WorkerSettings.model_fields["training_max_memory_mb"].default * MIB
    assert training_bound < quantity(trainer["resources"]["limits"]["memory"])
    assert quantity(trainer["resources"]["requests"]["memory"]) >= 3_715_000_000  # a training's measured peak
    base_limit = container(base(), "Deployment", "precond-worker")["resources"]["limits"]["memory"]
    assert quantity(base_limit) <= 1_350_000_000


def test_a_serving_pod_converts_the_model_before_its_worker_starts(rendered: list[Resource]) -> None:
    """The one-time conversion holds a full-width copy: an init container does it under its own limit, into
    the volume the worker reads, with the worker's environment."""
    spec = pod_spec(rendered, "Deployment", "precond-worker")
    [init] = spec["initContainers"]
    assert init["command"] == ["precond", "prepare-model"]
    assert "prepare-model" in {command.name for command in cli_app.registered_commands}
    assert init["envFrom"] == spec["containers"][0]["envFrom"] and init["image"] == spec["containers"][0]["image"]
    config = named(rendered, "ConfigMap", "precond-config")["data"]
    assert {m["mountPath"] for m in init["volumeMounts"]} == {"/tmp", config["MODEL_CACHE_DIR"]}
    assert quantity(init["resources"]["limits"]["memory"]) > 4_362 * MIB  # a first start's measured peak


def test_the_worker_healthcheck_knows_which_queues_need_the_model() -> None:
    text = (ROOT / "docker" / "healthcheck.py").read_text()
    spelt = re.search(r"^SERVING_QUEUE = (\".*\")$", text, flags=re.MULTILINE)
    assert spelt and eval(spelt.group(1)) == MODEL_QUEUE


def test_gateways_scale_on_cpu(rendered: list[Resource]) -> None:
    hpa = named(rendered, "HorizontalPodAutoscaler", "precond-gateway")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment", "name": "precond-gateway"}
    (metric,) = hpa["spec"]["metrics"]
    assert metric["resource"]["name"] == "cpu" and metric["resource"]["target"]["type"] == "Utilization"
    gateway = container(rendered, "Deployment", "precond-gateway")
    assert gateway["resources"]["requests"]["cpu"], "utilisation is a share of the request"
    assert "replicas" not in named(rendered, "Deployment", "precond-gateway")["spec"], "the HPA owns it"


def test_gateways_and_workers_have_disruption_budgets(rendered: list[Resource]) -> None:
    budgets = [r for r in rendered if r["kind"] == "PodDisruptionBudget"]
    for name in ("precond-gateway", *WORKERS):
        labels = named(rendered, "Deployment", name)["spec"]["template"]["metadata"]["labels"]
        assert any(b["spec"]["selector"]["matchLabels"].items() <= labels.items() for b in budgets), name


# ---- locked down ------------------------------------------------------------------------------------------


def test_every_container_is_non_root_read_only_and_without_capabilities(rendered: list[Resource]) -> None:
    for resource in rendered:
        for spec in pod_specs(resource):
            pod = spec["securityContext"]
            assert pod["runAsNonRoot"] is True and pod["runAsUser"] != 0, resource["metadata"]["name"]
            assert pod["seccompProfile"] == {"type": "RuntimeDefault"}
            assert spec["automountServiceAccountToken"] is False
            for one in spec["containers"]:
                context = one["securityContext"]
                assert context["allowPrivilegeEscalation"] is False and context["readOnlyRootFilesystem"] is True
                assert context["capabilities"] == {"drop": ["ALL"]}, "the sandbox needs no capability"
                assert context.get("privileged") is False
                limits, requests = one["resources"]["limits"], one["resources"]["requests"]
                assert limits["memory"] and requests["memory"] and requests["cpu"]
                assert one["livenessProbe"] and one["readinessProbe"]
            for one in spec.get("initContainers", []):
                context = one["securityContext"]
                assert context["allowPrivilegeEscalation"] is False and context["readOnlyRootFilesystem"] is True
                assert context["capabilities"] == {"drop": ["ALL"]} and context.get("privileged") is False
                assert one["resources"]["limits"]["memory"] and one["resources"]["requests"]["memory"]


@pytest.mark.parametrize("name", WORKERS)
def test_the_worker_never_runs_unconfined_and_writes_only_its_volumes(rendered: list[Resource], name: str) -> None:
    worker = container(rendered, "Deployment", name)
    assert {"name": "SANDBOX_ALLOW_UNCONFINED", "value": "false"} in worker["env"]
    writable = {m["mountPath"] for m in worker["volumeMounts"] if not m.get("readOnly")}
    config = named(rendered, "ConfigMap", "precond-config")["data"]
    assert writable == {"/tmp", config["MODEL_CACHE_DIR"]}
    volumes = {v["name"]: v for v in pod_spec(rendered, "Deployment", name)["volumes"]}
    for mount in worker["volumeMounts"]:
        if not mount.get("readOnly"):
            assert volumes[mount["name"]]["emptyDir"]["sizeLimit"], mount
    gateway = container(rendered, "Deployment", "precond-gateway")
    assert all(mount.get("readOnly") for mount in gateway["volumeMounts"]), "the gateway writes no file"


def mounted_secret_keys(spec: dict[str, Any]) -> set[str]:
    return {item["key"] for volume in spec["volumes"] if "secret" in volume for item in volume["secret"]["items"]}


def test_each_pod_mounts_only_the_secrets_it_reads(rendered: list[Resource]) -> None:
    """Gateways and workers their own role's Redis passwords; a Redis server its ACL lines (digests only) and
    its probe's password."""
    for name, (role, _) in ROLE_OF.items():
        own = {password_file("queue", role), password_file("cache", role), "precond-secret"}
        api_keys = {"api-keys.jsonl"} if role == "gateway" else set()  # a worker never authenticates callers
        assert mounted_secret_keys(pod_spec(rendered, "Deployment", name)) == own | api_keys, name
    for kind, name, server in (("StatefulSet", "precond-redis", "queue"),
                               ("Deployment", "precond-redis-cache", "cache")):
        assert mounted_secret_keys(pod_spec(rendered, kind, name)) == {acl_file(server),
                                                                      password_file(server, "probe")}


def test_the_redis_servers_are_bounded_and_have_a_user_per_role(rendered: list[Resource]) -> None:
    queue = " ".join(container(rendered, "StatefulSet", "precond-redis")["command"])
    cache = " ".join(container(rendered, "Deployment", "precond-redis-cache")["command"])
    assert "--appendonly yes" in queue and "--maxmemory-policy noeviction" in queue and "--dir /data" in queue
    assert "--appendonly no" in cache and "--maxmemory-policy allkeys-lru" in cache
    for command, kind, name, server in ((queue, "StatefulSet", "precond-redis", "queue"),
                                        (cache, "Deployment", "precond-redis-cache", "cache")):
        assert f"$(cat /secrets/{acl_file(server)})" in command and re.search(r"--maxmemory \d+mb", command)
        assert "requirepass" not in command  # no default user: every client names its own
        for probe in ("readinessProbe", "livenessProbe"):
            check = " ".join(container(rendered, kind, name)[probe]["exec"]["command"])
            assert f"/secrets/{password_file(server, 'probe')}" in check and "--user probe" in check
    claim = named(rendered, "StatefulSet", "precond-redis")["spec"]["volumeClaimTemplates"][0]
    assert claim["metadata"]["name"] == "data"


# ---- network ----------------------------------------------------------------------------------------------


def pods(rendered: list[Resource]) -> dict[str, Pod]:
    namespace_labels = {"kubernetes.io/metadata.name": NAMESPACE}
    found = {}
    for resource in rendered:
        for _ in pod_specs(resource):
            labels = resource["spec"]["template"]["metadata"]["labels"]
            found[labels["app.kubernetes.io/component"]] = Pod(NAMESPACE, labels, namespace_labels)
    found["neighbour"] = Pod(NAMESPACE, {"app": "something-else"}, namespace_labels)
    found["other namespace"] = Pod("shop", {"app.kubernetes.io/component": "gateway"},
                                   {"kubernetes.io/metadata.name": "shop"})
    found["keda"] = Pod("keda", {"app": "keda-operator"}, {"kubernetes.io/metadata.name": "keda"})
    return found


def test_only_gateways_and_workers_reach_redis_and_nothing_reaches_a_worker(rendered: list[Resource]) -> None:
    policies = [r for r in rendered if r["kind"] == "NetworkPolicy"]
    everyone = pods(rendered)
    assert {"gateway", "worker", "trainer", "queue-redis", "cache-redis"} <= set(everyone)
    allowed = {(source, destination, port) for source in everyone for destination in everyone
               for port in (6379, 8000, 9999) if source != destination
               and destination in ("gateway", "worker", "trainer", "queue-redis", "cache-redis")
               and can_connect(policies, everyone[source], everyone[destination], port)}
    servers = {(s, d, 6379) for s in ("gateway", "worker", "trainer") for d in ("queue-redis", "cache-redis")}
    # pods of other namespaces call the gateways; this namespace's other pods (and the workers) are denied
    # every egress but what a policy names
    callers = {("other namespace", "gateway", 8000), ("keda", "gateway", 8000)}
    assert allowed == servers | callers | {("keda", "queue-redis", 6379)}

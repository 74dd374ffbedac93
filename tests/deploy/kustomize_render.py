"""The part of kustomize that deploy/kubernetes/ uses, in Python, so that the manifests' tests render the
overlays on a machine without kubectl (test_manifests.py compares it with `kubectl kustomize` where kubectl
is installed).

A kustomization here may say only `resources` (files or directories), `namespace`, `images` (newName,
newTag), `patches` given inline as JSON 6902 operations on a target named by kind and a name regex, and
`sortOptions: {order: fifo}`. Anything else raises Unsupported, so a manifest that starts using another
feature fails its tests here instead of being rendered wrong.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import yaml

Resource = dict[str, Any]
SUPPORTED = {"apiVersion", "kind", "resources", "namespace", "images", "patches", "sortOptions"}
CLUSTER_SCOPED = {"Namespace", "ClusterRole", "ClusterRoleBinding", "CustomResourceDefinition", "PriorityClass"}


class Unsupported(ValueError):
    """A kustomization feature this renderer does not implement."""


class PatchError(ValueError):
    """A patch whose target or path does not exist: kustomize refuses it too."""


def load_documents(path: Path) -> list[Resource]:
    return [doc for doc in yaml.safe_load_all(path.read_text()) if doc]


def render(directory: Path) -> list[Resource]:
    """The resources `kubectl kustomize DIRECTORY` prints, in its fifo order."""
    kustomization = yaml.safe_load((directory / "kustomization.yaml").read_text())
    unknown = set(kustomization) - SUPPORTED
    if unknown:
        raise Unsupported(f"{directory}: {sorted(unknown)}")
    if kustomization.get("sortOptions", {"order": "fifo"}) != {"order": "fifo"}:
        raise Unsupported(f"{directory}: sortOptions other than fifo")
    resources: list[Resource] = []
    for entry in kustomization.get("resources", []):
        path = directory / entry
        resources += render(path) if path.is_dir() else load_documents(path)
    for patch in kustomization.get("patches", []):
        apply_patch(resources, patch)
    if "namespace" in kustomization:
        for resource in resources:
            if resource["kind"] not in CLUSTER_SCOPED:
                resource["metadata"]["namespace"] = kustomization["namespace"]
    for image in kustomization.get("images", []):
        set_image(resources, image)
    return resources


def apply_patch(resources: list[Resource], patch: dict[str, Any]) -> None:
    if set(patch) != {"target", "patch"} or set(patch["target"]) - {"kind", "name"}:
        raise Unsupported(f"patch {patch}: only an inline patch on a kind and name")
    target = patch["target"]
    matched = [r for r in resources if r["kind"] == target["kind"]
               and re.fullmatch(target.get("name", ".*"), r["metadata"]["name"])]
    if not matched:
        raise PatchError(f"no resource matches {target}")
    operations = yaml.safe_load(patch["patch"])
    if not isinstance(operations, list):
        raise Unsupported(f"patch on {target}: only JSON 6902 operations")
    for resource in matched:
        for operation in operations:
            apply_operation(resource, operation)


def apply_operation(document: Resource, operation: dict[str, Any]) -> None:
    op, path = operation["op"], operation["path"]
    if op not in ("add", "replace", "remove"):
        raise Unsupported(f"JSON patch operation {op}")
    *parents, last = [part.replace("~1", "/").replace("~0", "~") for part in path.split("/")[1:]]
    node: Any = document
    for part in parents:
        try:
            node = node[int(part)] if isinstance(node, list) else node[part]
        except (KeyError, IndexError, ValueError) as exc:
            raise PatchError(f"{path}: no {part!r}") from exc
    if isinstance(node, list):
        index = len(node) if last == "-" else int(last)
        if op == "add":
            node.insert(index, copy.deepcopy(operation["value"]))
            return
        if index >= len(node):
            raise PatchError(f"{path}: no item {index}")
        if op == "remove":
            del node[index]
        else:
            node[index] = copy.deepcopy(operation["value"])
        return
    if op != "add" and last not in node:
        raise PatchError(f"{path}: no {last!r} to {op}")
    if op == "remove":
        del node[last]
    else:
        node[last] = copy.deepcopy(operation["value"])


def pod_specs(resource: Resource) -> list[dict[str, Any]]:
    template = resource.get("spec", {}).get("template")
    return [template["spec"]] if template else []


def set_image(resources: list[Resource], image: dict[str, str]) -> None:
    if set(image) - {"name", "newName", "newTag"}:
        raise Unsupported(f"images entry {image}")
    for resource in resources:
        for spec in pod_specs(resource):
            for container in spec.get("initContainers", []) + spec["containers"]:
                name, _, tag = container["image"].partition(":")
                if name == image["name"]:
                    tag = image.get("newTag", tag)
                    container["image"] = image.get("newName", name) + (f":{tag}" if tag else "")

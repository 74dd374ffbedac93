"""The Kubernetes manifests as the tests read them: rendered base and overlays, and what is in their pods."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from kustomize_render import Resource, pod_specs, render

ROOT = Path(__file__).resolve().parents[2]
KUBERNETES = ROOT / "deploy" / "kubernetes"
BASE = KUBERNETES / "base"
OVERLAYS = sorted(path.parent for path in (KUBERNETES / "overlays").glob("*/kustomization.yaml"))
TARGETS = [BASE, *OVERLAYS]
"""Every directory `kubectl apply -k` may be given."""


def named(resources: list[Resource], kind: str, name: str) -> Resource:
    (found,) = [r for r in resources if r["kind"] == kind and r["metadata"]["name"] == name]
    return found


def container(resources: list[Resource], kind: str, name: str) -> dict[str, Any]:
    (spec,) = pod_specs(named(resources, kind, name))
    (only,) = spec["containers"]
    return dict(only)


def pod_spec(resources: list[Resource], kind: str, name: str) -> dict[str, Any]:
    (spec,) = pod_specs(named(resources, kind, name))
    return spec


def base() -> list[Resource]:
    return render(BASE)

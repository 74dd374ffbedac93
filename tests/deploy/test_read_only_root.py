"""readOnlyRootFilesystem, simulated: gateway and worker serve real jobs in a mount namespace whose root is
read-only, the worker writing only under /tmp (the manifests give it /tmp and /models volumes, which
test_manifests.py checks) and the gateway nowhere, as its pod gives it no writable volume."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.stack

HERE = Path(__file__).parent
ROOT = HERE.parents[1]


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None,
                    reason="a private mount namespace needs root and unshare(1)")
def test_gateway_and_worker_serve_on_a_read_only_root(tmp_path: Path, tiny_model_dir: Path) -> None:
    read_only_root = 'mount --bind /tmp /tmp && mount -o remount,bind,ro / && exec "$@"'
    done = subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "sh", "-c", read_only_root, "read-only-root",
         sys.executable, str(HERE / "read_only_probe.py"), str(tmp_path), str(tiny_model_dir)],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=400,
    )
    logs = "\n".join(f"{p.name}: {p.read_text()[-1500:]}" for p in tmp_path.glob("*.log"))
    assert done.returncode == 0, done.stderr[-3000:] + logs
    outcomes = json.loads(done.stdout)
    assert outcomes == {"check": "succeeded", "long check": "succeeded", "enumerate": "succeeded",
                        "model": "succeeded"}, logs


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None,
                    reason="a private mount namespace needs root and unshare(1)")
def test_a_worker_pod_without_its_tmp_volume_refuses_untrusted_code_and_says_why() -> None:
    done = subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "sh", "-c", 'mount -o remount,bind,ro / && exec "$@"',
         "read-only-root", sys.executable, "-m", "precond.sandbox.selfcheck"],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=60,
    )
    report = json.loads(done.stdout)
    assert done.returncode == 1 and report["confined"] is False
    assert "No usable temporary directory" in report["reason"]

"""The sandbox run as another user, the way tests attack it as a non-root worker (or a pod) runs it: a copy of
what the sandbox imports that every user can read, and an interpreter that user may execute (the project's
own may live under a private home)."""

from __future__ import annotations

import shutil
import stat
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SPAWNS_ITSELF = ("import subprocess, sys; "
                 "subprocess.run([sys.executable, '-I', '-S', '-c', 'import ctypes'], check=True)")


def readable_sandbox_copy(where: Path, extra_files: Iterable[Path] = ()) -> Path:
    """Copy the sandbox, its program reader, the hostile corpus, the policy binding and `extra_files` into
    `where`, readable by any user; `PYTHONPATH=where` then imports them from there."""
    import pyseccomp

    package = where / "precond"
    package.mkdir(parents=True)
    shutil.copy(ROOT / "precond" / "__init__.py", package)
    for name in ("sandbox", "programs"):
        shutil.copytree(ROOT / "precond" / name, package / name, ignore=shutil.ignore_patterns("__pycache__"))
    (package / "stack").mkdir()
    for name in ("__init__.py", "hostile_corpus.py"):
        shutil.copy(ROOT / "precond" / "stack" / name, package / "stack")
    for path in (Path(pyseccomp.__file__), *extra_files):
        shutil.copy(path, where)
    for path in [where, *where.rglob("*")]:
        path.chmod(path.stat().st_mode | stat.S_IROTH | (stat.S_IXOTH if path.is_dir() else 0))
    return where


def runnable_python(setpriv: list[str]) -> str:
    """An interpreter that `setpriv` (the identity's options) may execute, and that may start itself again
    (as the sandbox's fork servers are started)."""
    for candidate in (sys.executable, shutil.which("python3"), "/usr/bin/python3"):
        if candidate and subprocess.run(["setpriv", *setpriv, candidate, "-c", SPAWNS_ITSELF],
                                        capture_output=True, check=False).returncode == 0:
            return candidate
    raise AssertionError(f"no Python interpreter can be run as `setpriv {' '.join(setpriv)}`")

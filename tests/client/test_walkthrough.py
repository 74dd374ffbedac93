"""examples/walkthrough.py, the worked example of docs/writing-a-spec.md, run as a user runs it against a
real keyed stack: it checks each step's answer itself and exits non-zero when the guide no longer holds."""

from __future__ import annotations

import os
import subprocess
import sys

from precond.stack.keyed import KeyedStack
from precond.stack.local import ROOT


def test_the_walkthrough_runs_end_to_end(keyed: KeyedStack) -> None:
    env = {**os.environ, "PRECOND_API_KEY": keyed.keys["walkthrough"]}
    done = subprocess.run([sys.executable, "examples/walkthrough.py", "--server", keyed.url], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip().endswith("walkthrough: ok"), done.stdout + done.stderr
    assert "system.FindBooks(): refused" in done.stdout

"""`precond ARGS` run in the test's own process (click's runner): what a command prints on stdout and stderr and
its exit code, as a `python -m precond.cli` child would give them, without a fresh interpreter's start-up for
each call. An exception the command lets out is raised here, so a command that would end in a traceback fails
its test. Commands that must be a real process (serve, a killed child) start one
themselves."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from precond.cli.main import app

ROOT = Path(__file__).resolve().parents[2]


def precond(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    """The command's outcome, run from the checkout's root as the console script would be."""
    with contextlib.chdir(ROOT):
        result = CliRunner().invoke(app, list(args), input=stdin, catch_exceptions=False, prog_name="precond")
    return subprocess.CompletedProcess([sys.executable, "-m", "precond.cli", *args], result.exit_code,
                                       result.stdout, result.stderr)

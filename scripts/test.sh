#!/usr/bin/env bash
# Install, then lint, type-check and run the test suite (the README's test command; CI runs exactly this) in
# two steps: the fast suite (`-m "not model and not stack"`), then the tests that start real stacks, pod
# simulations and fresh installs (`-m stack`) together with those that run the real embedded model (`-m model`):
# the model's tests are single-threaded and CPU-bound, the stacks' tests mostly wait for processes, so they share
# the cores, and mypy runs beside them. The property tests that draw many hypothesis examples (`-m generated`)
# run a tenth of them in the fast step and all of them in the second.
# Both steps run two test processes a core (pytest-xdist `-n`): much of each waits (for child processes, sockets,
# the sandbox's wall-clock limits), and a core's second process fills those waits (on a fresh clone of 2 cores,
# one process a core took the fast step from 132 s to 202 s, though it spends less CPU: each process pays its own
# collection, about 6 CPU s). PYTEST_XDIST_AUTO_NUM_WORKERS sets both. A test file per process (`--dist loadfile`: a module's stack is
# started once, in the process that runs it); the fast step hands them out in the order collected
# (`--no-loadscope-reorder`), the files marked `long` first (tests/conftest.py), so that none of them starts last
# and ends the step alone on one core.
# One step alone: `python -m pytest -q -m "not model and not stack"` after `. .venv/bin/activate` (add `-n auto`).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 TOKENIZERS_PARALLELISM=false
# Compiled modules, pytest's rewritten test modules among them, are kept (__pycache__/, ignored by git): every
# pytest process and every process a stack starts reads them instead of compiling the sources again.
unset PYTHONDONTWRITEBYTECODE
# The embedded model's converted copies (MODEL_CACHE_DIR; minutes, once a machine) are built beside the lint and
# the fast step; else the model tests' processes would each build them at once.
precond prepare-model &
prepared=$!
# One collection beside them writes those compiled modules before the steps' processes each need them (a
# collection error is reported by the steps).
python -m pytest --collect-only -q -p no:xdist >/dev/null 2>&1 &
collected=$!
ruff check .
wait "$collected" || true

pytest_step() {
  # $1: test processes. Exit code 5 means "no tests collected" (e.g. arguments that select no model test): not a
  # failure.
  local processes=$1 code=0
  shift
  python -m pytest -q -n "$processes" --dist loadfile "$@" || code=$?
  if [ "$code" -eq 5 ]; then
    code=0
  fi
  return "$code"
}

# mypy is one process on one core (a minute without its cache, as on a fresh clone): it runs beside the second
# step, whose processes mostly wait, rather than beside the fast step, whose processes compute; its report is
# printed at the end, and a mypy failure fails the run with mypy's exit code (after the fast step's failure, if
# that failed: mypy still runs then, so that one run reports both).
typecheck_log=$(mktemp)
trap 'rm -f "$typecheck_log"' EXIT
typecheck() {
  local code=0
  wait "$1" || code=$?
  cat "$typecheck_log"
  if [ "$code" -ne 0 ]; then
    echo "mypy failed (exit $code)" >&2
  fi
  return "$code"
}

fast=0
pytest_step "${PYTEST_XDIST_AUTO_NUM_WORKERS:-$((2 * $(nproc)))}" --no-loadscope-reorder -m "not model and not stack" \
  --examples-share 0.1 "$@" || fast=$?
mypy >"$typecheck_log" 2>&1 &
typed=$!
if [ "$fast" -ne 0 ]; then
  typecheck "$typed" || true
  exit "$fast"
fi
wait "$prepared"
second=0
pytest_step "${PYTEST_XDIST_AUTO_NUM_WORKERS:-$((2 * $(nproc)))}" -m "stack or model or generated" "$@" || second=$?
typecheck "$typed"
exit "$second"

#!/usr/bin/env bash
# Install, then lint, type-check and run the test suite (the README's test command; CI runs exactly this) in
# two steps: the fast suite (`-m "not model and not stack"`), then the tests that start real stacks, pod
# simulations and fresh installs (`-m stack`) together with those that run the real embedded model (`-m model`):
# the model's tests are single-threaded and CPU-bound, the stacks' tests mostly wait for processes, so they share
# the cores. Each step runs on every core (pytest-xdist, `-n auto`; PYTEST_XDIST_AUTO_NUM_WORKERS sets how many),
# a test file per process (`--dist loadfile`: a module's stack is started once, in the process that runs it).
# One step alone: `python -m pytest -q -m "not model and not stack"` after `. .venv/bin/activate` (add `-n auto`).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 TOKENIZERS_PARALLELISM=false
# The embedded model's converted copies (MODEL_CACHE_DIR; minutes, once a machine) are built beside the lint and
# the type check, on a core they leave idle; else the model tests' processes would each build them at once.
precond prepare-model &
prepared=$!
ruff check .
mypy
wait "$prepared"

pytest_step() {
  # Exit code 5 means "no tests collected" (e.g. arguments that select no model test): not a failure.
  local code=0
  python -m pytest -q -n auto --dist loadfile "$@" || code=$?
  if [ "$code" -eq 5 ]; then
    code=0
  fi
  return "$code"
}

pytest_step -m "not model and not stack" "$@"
pytest_step -m "stack or model" "$@"

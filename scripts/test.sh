#!/usr/bin/env bash
# Install, then lint, type-check and run the test suite (the README's test command; CI runs exactly this) in
# three steps: the fast suite (`-m "not model and not stack"`), then the tests that start real stacks, pod
# simulations and fresh installs (`-m stack`), then those that run the real embedded model (`-m model`).
# One step alone: `python -m pytest -q -m "not model and not stack"` after `. .venv/bin/activate`.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 TOKENIZERS_PARALLELISM=false
ruff check .
mypy

pytest_step() {
  # Exit code 5 means "no tests collected" (e.g. arguments that select no model test): not a failure.
  local code=0
  python -m pytest -q "$@" || code=$?
  if [ "$code" -eq 5 ]; then
    code=0
  fi
  return "$code"
}

pytest_step -m "not model and not stack" "$@"
pytest_step -m stack "$@"
pytest_step -m model "$@"

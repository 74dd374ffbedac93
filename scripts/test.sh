#!/usr/bin/env bash
# Install, then lint, type-check and run the test suite (the README's test command; CI runs exactly this):
# the fast suite first, then the tests that run the real embedded model (`-m model`) as their own step.
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

pytest_step -m "not model" "$@"
pytest_step -m model "$@"

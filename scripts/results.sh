#!/usr/bin/env bash
# Regenerate docs/results.md from scratch: every precondition config (with the embedded model: ~20 min on a
# 2-core CPU), a policy sample (~20 min), the sandbox benchmark, then the report. Runs are cached per domain
# and config under .eval-cache/, so an interrupted run resumes where it stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 TOKENIZERS_PARALLELISM=false
precond eval preconditions --data ../shared/data/sgd --data ../shared/data/alfworld --configs default
precond eval preconditions --data ../shared/data/sgd --configs noise   # strict vs tolerant under errors and few demos
precond eval policy --data ../shared/data/sgd --domains "${POLICY_DOMAINS:-Buses_1,Restaurants_1}" \
  --dialogs "${POLICY_DIALOGS:-2}" --turns "${POLICY_TURNS:-6}" --configs default
precond eval all

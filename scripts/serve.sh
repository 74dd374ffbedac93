#!/usr/bin/env bash
# Install (pip only when something changed), then serve: two private Redis (or REDIS_URL / --redis-url), a worker
# with the embedded model, the gateway on $PORT (8000 unless set; `PORT` is a gateway setting, see
# docs/configuration.md). Arguments go to `precond serve` (e.g. --redis-url URL, --workers N, --no-rate-limit to
# lift the open tenant's request rate for local use).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
cat <<MSG
Starting the service on http://127.0.0.1:${PORT:-8000} (first start converts the embedded model once, ~1 min).
It names the Redis it uses, and says when it is ready (GET /ready answers 200). Then try (the rules, their
evidence and warnings; "candidates": "all" also lists every dropped candidate with why, 0.6-0.8 MB):
  curl -s -X POST "http://127.0.0.1:${PORT:-8000}/infer-preconditions?wait=60" \\
       -H 'Content-Type: application/json' -d @examples/infer-kept.json | python -m json.tool
MSG
exec precond serve "$@"

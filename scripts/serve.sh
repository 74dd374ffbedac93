#!/usr/bin/env bash
# Install, then serve: Redis (started if none answers), a worker with the embedded model, the gateway on :8000.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
PORT=${PORT:-8000}
cat <<MSG
Starting the service on http://127.0.0.1:${PORT} (first start converts the embedded model once, ~1 min).
Try, once it answers /ready:
  curl -s -X POST "http://127.0.0.1:${PORT}/infer-preconditions?wait=60" \\
       -H 'Content-Type: application/json' -d @examples/infer-enumerate.json | python -m json.tool
MSG
exec precond serve --port "$PORT" "$@"

#!/usr/bin/env bash
# Install, then serve: Redis (started if none answers), a worker with the embedded model, the gateway on $PORT
# (8000 unless set; `PORT` is a gateway setting, see docs/configuration.md).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install.sh
. .venv/bin/activate
cat <<MSG
Starting the service on http://127.0.0.1:${PORT:-8000} (first start converts the embedded model once, ~1 min).
It prints one line "precond: ready at ..." once /ready answers. Then try:
  curl -s -X POST "http://127.0.0.1:${PORT:-8000}/infer-preconditions?wait=60" \\
       -H 'Content-Type: application/json' -d @examples/infer-enumerate.json | python -m json.tool
MSG
exec precond serve "$@"

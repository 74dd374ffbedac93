#!/usr/bin/env bash
# Install everything the service, its worker and its tests need into ./.venv (idempotent).
# The Dockerfiles run this same script, so the images are built exactly as the tests are run.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
EXTRAS=${PRECOND_EXTRAS:-model,eval,dev}

if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
. .venv/bin/activate
# pip runs again only when what it installs could differ: this script, pyproject.toml, the extras or the torch
# index changed since the last install into this .venv (scripts/serve.sh runs this script at every start).
STAMP=.venv/.precond-installed
WANT="$(cat scripts/install.sh pyproject.toml | sha256sum | cut -d' ' -f1) extras=${EXTRAS} index=${TORCH_INDEX:-}"
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ]; then
  echo "install: .venv already has this version's packages; pip skipped (delete $STAMP to reinstall)" >&2
else
  python -m pip install --quiet --upgrade pip
  # torch first and pinned: an unpinned torch pulls several GB of CUDA packages. TORCH_INDEX names a CPU
  # wheel index where no local wheel is configured (the Dockerfile sets it).
  python -m pip install --quiet "torch==2.13.0" ${TORCH_INDEX:+--extra-index-url "$TORCH_INDEX"}
  python -m pip install --quiet -e ".[${EXTRAS}]"
  echo "$WANT" > "$STAMP"
fi

# The sandbox's kernel policy is built with libseccomp; without it no untrusted code runs (fail closed).
if ! ldconfig -p 2>/dev/null | grep -q 'libseccomp\.so\.2'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    apt-get update -qq && apt-get install -y -qq libseccomp2 >/dev/null
  else
    echo "warning: libseccomp2 not found; install it, or the sandbox refuses to run untrusted code" >&2
  fi
fi

# Redis is needed by the service and its tests (not by an image whose Redis runs apart: PRECOND_INSTALL_REDIS=0);
# install the server where none is on PATH.
if [ "${PRECOND_INSTALL_REDIS:-1}" = 1 ] && ! command -v redis-server >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    apt-get update -qq && apt-get install -y -qq redis-server >/dev/null
  else
    echo "warning: redis-server not found; install it (e.g. apt-get install redis-server)" >&2
  fi
fi

# The review page (/ui/) is tested in a real browser: Debian's Chromium, driven by Playwright (a dev extra) with
# `executable_path` (Playwright's own browser download is not used). Only where the dev extra is installed.
if [[ ",${EXTRAS}," == *",dev,"* ]] && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    apt-get update -qq && apt-get install -y -qq chromium >/dev/null
  else
    echo "warning: chromium not found; the review page's browser tests will be skipped (apt-get install chromium)" >&2
  fi
fi

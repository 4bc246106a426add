#!/usr/bin/env bash
# Creates .venv and installs the pinned dependencies (requirements.lock) and rllock itself.
# Re-runs only when requirements.lock or pyproject.toml change. Needs only Python 3.11+.
# Then compiles rllock's numba code into its cache (a no-op load when nothing changed).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { echo "rllock needs Python 3.11 or newer" >&2; exit 1; }
stamp_value="$(cat requirements.lock pyproject.toml | "$PY" -c 'import hashlib,sys; print(hashlib.sha256(sys.stdin.buffer.read()).hexdigest())')"
if [ ! -x .venv/bin/python ] || [ "$(cat .venv/.install-stamp 2>/dev/null)" != "$stamp_value" ]; then
  echo "installing dependencies into .venv (first run takes a few minutes)" >&2
  "$PY" -m venv .venv
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -r requirements.lock
  .venv/bin/python -m pip install --quiet --no-deps -e .
  echo "$stamp_value" > .venv/.install-stamp
fi
# Compile the sampler and checkers into numba's cache now (about two minutes on a cold cache on 2 cores,
# a few seconds when warm), not inside the first command's time limit (rllock/core/precompile.py).
.venv/bin/python -m rllock.core.precompile

#!/usr/bin/env bash
# The test suite: installs what it needs, runs ruff (lint, format) and mypy (the core), then pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# The HTML viewer test renders in headless Chromium (Debian's package); install it when we can.
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing chromium for the HTML viewer test" >&2
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "could not install chromium; the HTML rendering test will be skipped" >&2
fi
# Lint, format and type checks first: a style or type error fails fast, before the 10-minute suite.
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy
# Two workers: the tests that start Ray run in turn on one, the rest on the other (tests/conftest.py).
exec .venv/bin/python -m pytest -q -n 2 --dist loadgroup "$@"

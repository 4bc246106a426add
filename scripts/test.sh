#!/usr/bin/env bash
# The test suite: installs what it needs, runs ruff (lint, format) and mypy (the core), then pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# The HTML viewer and web page tests run headless Chromium and its driver (Debian's packages); install
# them when we can.
if ! { command -v chromium && command -v chromedriver; } >/dev/null 2>&1 && [ "$(id -u)" = 0 ] \
  && command -v apt-get >/dev/null 2>&1; then
  echo "installing chromium and chromium-driver for the browser tests" >&2
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null) \
    || echo "could not install chromium; the browser tests will be skipped" >&2
fi
# Lint, format and type checks first: a style or type error fails fast, before the minutes of pytest.
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy
# Two workers: the tests that start Ray run in turn on one, the rest on the other (tests/conftest.py).
exec .venv/bin/python -m pytest -q -n 2 --dist loadgroup "$@"

#!/usr/bin/env bash
# Rewrites docs/cli.md, the command reference, from the parser (tests/test_cli_reference.py checks it).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/python -c 'import sys; from rllock.orchestration.cli.main import reference; sys.stdout.write(reference())' > docs/cli.md

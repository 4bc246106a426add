"""`python -m rllock.orchestration.cli`: the `rllock` command."""

import sys

from rllock.orchestration.cli.main import entry

sys.exit(entry())

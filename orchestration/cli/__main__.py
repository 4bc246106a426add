"""`python -m orchestration.cli`: the `rllock` command."""

import sys

from orchestration.cli.main import main

sys.exit(main())

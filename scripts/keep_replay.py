"""Keep a guide run's replay snapshot in the repository: the searches a guide learns from outlive the
machine that made them.

Writes OUT (a compressed copy of RUN/replay.npz) and OUT with .json beside it (the run's config, counters
and sessions: command, commit, machine, date). `rllock train-guide --replay-from OUT,...` trains on it and
records that record in the guide's metadata (`rllock.orchestration.guide_offline`).

    python scripts/keep_replay.py runs/guide-mario-f data/replay/mario-f.npz
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from rllock.errors import RLLockError
from rllock.orchestration.guide_offline import keep_snapshot

log = logging.getLogger("keep_replay")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", force=True)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="a rllock train-guide run folder")
    p.add_argument("out", help="the .npz to write (its record: the same name with .json)")
    args = p.parse_args()
    try:
        record = keep_snapshot(Path(args.run), Path(args.out))
    except RLLockError as exc:
        p.exit(2, f"keep_replay: {exc}\n")
    log.info("%d states of %s kept in %s (sha256 %s)", record["states"], args.run, args.out, record["sha256"])


if __name__ == "__main__":
    main()

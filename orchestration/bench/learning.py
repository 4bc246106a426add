"""`rllock bench learning` (a checkpoint against the same search untrained) and `rllock bench success`
(checkpoints' success rates over many episodes, with Wilson 95% intervals).
"""

from __future__ import annotations

import logging
from typing import TypedDict

log = logging.getLogger("rllock")


class ArmRow(TypedDict):
    """One arm of `rllock bench learning`, as its JSON document holds it."""

    valid: int
    episodes: int
    seconds: float
    success_rate: float
    time_per_valid_s: float | None


def learning_ratio(
    trained: float | None, untrained: float | None, untrained_seconds: float
) -> tuple[float | None, float | None]:
    """(trained / untrained time per valid assembly, an upper bound on it when only the untrained arm
    found nothing: having found none in S seconds, it needs more than S per valid assembly)."""
    if trained is None:
        return None, None
    if untrained is None:
        return None, trained / untrained_seconds
    return trained / untrained, None

"""The benches' comma-separated lists, parsed in one place: task lists, counts and names."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

from rllock.errors import RLLockError

T = TypeVar("T")


def items(text: str, flag: str) -> list[str]:
    """The comma-separated items of `text`, stripped; an empty list is an error."""
    found = [item.strip() for item in text.split(",") if item.strip()]
    if not found:
        raise RLLockError(f"{flag} is empty: give a comma-separated list")
    return found


def parse_list(text: str | None, default: Sequence[T], parse_one: Callable[[str], T], flag: str) -> list[T]:
    """Each item of `text` parsed by `parse_one` (which raises RLLockError on a bad one); `default`
    when no list is given."""
    return list(default) if text is None else [parse_one(item) for item in items(text, flag)]


def counts(text: str, flag: str) -> tuple[int, ...]:
    """'1,2,4' -> (1, 2, 4): positive counts."""
    try:
        found = tuple(int(c) for c in items(text, flag))
    except ValueError:
        raise RLLockError(f"{flag} takes a comma-separated list of counts, got {text!r}") from None
    if min(found) < 1:
        raise RLLockError(f"{flag} counts must be at least 1")
    return found


def choices(text: str, flag: str, allowed: Sequence[str]) -> list[str]:
    """The items of `text`, each one of `allowed`."""
    found = items(text, flag)
    if any(item not in allowed for item in found):
        raise RLLockError(f"{flag}: expected a comma-separated list of {', '.join(allowed)}")
    return found

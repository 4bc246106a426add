"""Where numba keeps the compiled sampler, checkers and winding numbers: per user and per version of the
core's sources, not beside them.

Numba's default cache is the `__pycache__` folder beside each source file. A Ray job runs from an
uploaded copy of the repository (Ray leaves out what .gitignore names, `__pycache__` among it), unpacked
in a new folder on every node, so every job on every node compiled the search anew, for minutes, before
its first episode. Here the cache is `$XDG_CACHE_HOME/rllock/numba/<digest>` (`~/.cache/rllock/numba/...`),
where the digest is of every source file of `rllock.core` together: a copy of the same sources anywhere
on the machine finds what `scripts/install.sh` compiled, and a change to any of them (a compiled callee
in another file, a constant frozen into compiled code) compiles afresh instead of loading code older
than its sources. Numba's own `NUMBA_CACHE_DIR`, when set, still decides. Import this module before any
`@njit(cache=True)` of the core: numba picks a function's cache folder when it is decorated.

Each version of the sources compiles into a folder of its own, so every update would leave one behind:
a folder is marked when its version is imported (at most once a day), and the folders of
other versions unmarked for STALE_DAYS are removed (`prune`).
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import shutil
import time
from pathlib import Path
from types import FunctionType

from numba.core.caching import (
    CacheImpl,
    UserProvidedCacheLocator,
    _CacheLocator,
    _SourceFileBackedLocatorMixin,
)

CORE = Path(__file__).resolve().parent
STALE_DAYS = 30.0
USED = ".used"  # its modification time: when the folder's version was last imported
DAY = 86_400.0
DIGEST = re.compile(r"[0-9a-f]{16}")


def numba_cache_root() -> Path:
    """The folder that holds a folder per version of the core's sources: per user, outside the sources."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rllock" / "numba"


@functools.cache
def sources_digest(folder: Path) -> str:
    """A digest of the names and contents of `folder`'s Python files, together."""
    digest = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


class CoreSourcesLocator(_SourceFileBackedLocatorMixin, _CacheLocator):
    """The cache folder of a function of `rllock.core` (module docstring); other functions are left to
    numba's own locators. Numba still checks each file's content hash against its index."""

    def __init__(self, py_func: FunctionType, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(numba_cache_root() / sources_digest(Path(py_file).resolve().parent))

    def get_cache_path(self) -> str:
        return self._cache_path

    @classmethod
    def from_function(cls, py_func: FunctionType, py_file: str) -> CoreSourcesLocator | None:
        if Path(py_file).resolve().parent != CORE:
            return None
        # Returns None where the folder cannot be made or written: numba then tries its own locators.
        return super().from_function(py_func, py_file)


def prune(root: Path, current: str, now: float, stale_days: float = STALE_DAYS) -> list[Path]:
    """Mark `current`'s folder under `root` used (unless it was within a day) and remove the folders of
    other digests last used (or, unmarked, modified) more than `stale_days` before `now`. Returns those
    removed; names that are not digests are never touched."""
    marker = root / current / USED
    if not marker.exists() or now - marker.stat().st_mtime > DAY:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
        os.utime(marker, (now, now))
    removed = []
    for folder in root.iterdir():
        if folder.name == current or not folder.is_dir() or not DIGEST.fullmatch(folder.name):
            continue
        used = folder / USED
        if now - (used if used.exists() else folder).stat().st_mtime > stale_days * DAY:
            shutil.rmtree(folder, ignore_errors=True)  # another process may be removing it too
            removed.append(folder)
    return removed


def install() -> None:
    """Put the locator first, after numba's `NUMBA_CACHE_DIR` one (which yields when that is unset)."""
    classes = CacheImpl._locator_classes
    if CoreSourcesLocator not in classes:
        classes.insert(classes.index(UserProvidedCacheLocator) + 1, CoreSourcesLocator)
    if not os.environ.get("NUMBA_CACHE_DIR"):
        try:
            prune(numba_cache_root(), sources_digest(CORE), time.time())
        except OSError:  # an unwritable cache: numba then compiles in memory, as it would
            pass


install()

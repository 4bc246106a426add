"""Facts about this process that the actors, the replay buffer and the trainer report, and the set-up of
JAX's persistent compilation cache, which every `rllock` command makes before JAX compiles anything.

The cache keeps compiled programs on disk, per user, so that a second process finds what a first one
compiled: `$RLLOCK_JAX_CACHE` names its folder, or `off`; unset, it is `$XDG_CACHE_HOME/rllock/jax`
(`~/.cache/rllock/jax`), unless JAX's own `JAX_COMPILATION_CACHE_DIR` is set. JAX trusts what it reads
there (a cached program is code it runs), so the folder is made readable and writable by its owner only.
JAX does not cache a program that calls back to the host, as the tree search does
(`rllock.search.mcts`): that one is compiled in every process.
"""

from __future__ import annotations

import logging
import os
import resource
import sys
from pathlib import Path

log = logging.getLogger(__name__)

JAX_CACHE_VARIABLE = "RLLOCK_JAX_CACHE"
JAX_CACHE_MAX_BYTES = 1 << 30  # least recently used programs go first beyond this
_OFF = ("off", "0", "false", "no", "none")


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, in MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def default_jax_cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rllock" / "jax"


def setup_jax_cache() -> Path | None:
    """Turn JAX's persistent compilation cache on (or off) as `$RLLOCK_JAX_CACHE` says, for this process
    and the processes it starts (Ray's actors inherit the environment); returns the folder, None when
    off. Call it before JAX compiles anything: JAX opens the cache at its first compile."""
    value = os.environ.get(JAX_CACHE_VARIABLE, "").strip()
    settings: dict[str, bool | int | float | str]
    if value.lower() in _OFF:
        path = None
        settings = {"jax_enable_compilation_cache": False}
    else:
        # Absolute: Ray's actors, which inherit it, run in folders of their own.
        chosen = value or os.environ.get("JAX_COMPILATION_CACHE_DIR") or default_jax_cache_dir()
        path = Path(chosen).expanduser().absolute()
        try:
            path.mkdir(mode=0o700, parents=True, exist_ok=True)
        except OSError as exc:
            log.warning("compiling without a persistent cache: cannot create %s (%s)", path, exc.strerror)
            return None
        settings = {
            "jax_enable_compilation_cache": True,
            "jax_compilation_cache_dir": str(path),
            # Every program, however small or quick to compile: a start-up pays for many small ones.
            "jax_persistent_cache_min_compile_time_secs": 0.0,
            "jax_persistent_cache_min_entry_size_bytes": -1,
            # A size limit also makes JAX lock the folder while it reads or writes an entry, which
            # processes compiling the same programs at once (Ray's actors) need.
            "jax_compilation_cache_max_size": JAX_CACHE_MAX_BYTES,
        }
    for name, setting in settings.items():
        os.environ[name.upper()] = str(setting).lower() if isinstance(setting, bool) else str(setting)
    if "jax" in sys.modules:  # JAX reads the environment when imported: tell it directly
        import jax

        for name, setting in settings.items():
            jax.config.update(name, setting)
    return path


def jax_cache_entries() -> int | None:
    """How many compiled programs JAX's persistent cache holds now (its files named KEY-cache), or None
    when this process has no cache."""
    import jax

    settings = jax.config.values
    folder = settings["jax_compilation_cache_dir"]
    if not settings["jax_enable_compilation_cache"] or not folder:
        return None
    path = Path(folder)
    return sum(1 for _ in path.glob("*-cache")) if path.is_dir() else 0

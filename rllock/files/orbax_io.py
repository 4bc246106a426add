"""Orbax reading and writing of a checkpoint's `state/` and `meta/` items, and the one-line errors of a
damaged checkpoint (orbax and TensorStore otherwise bury them under tracebacks and spec dumps)."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import logging
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp

from rllock.errors import RLLockError


def manager(directory: Path, keep: int) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        directory.absolute(),
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True),
        item_names=("state", "meta"),
    )


def save(mngr: ocp.CheckpointManager, step: int, state: Any, metadata: dict) -> None:
    """Save and wait; an earlier save of the same step (its metadata may be stale) is replaced.

    The replacement is written beside the folder and exchanged with the old step in one rename, so
    that a process killed meanwhile (or a reader polling the folder) never finds the step missing:
    deleting it first left a run whose only checkpoint was that step with none for the whole save, and
    two renames (old away, new in) still left a moment without it."""
    if step not in mngr.all_steps():
        _save(mngr, step, state, metadata)
        return
    folder = Path(mngr.directory)
    staging = folder.parent / f".{folder.name}-{step}-staging"
    shutil.rmtree(staging, ignore_errors=True)
    writer = manager(staging, keep=1)
    try:
        _save(writer, step, state, metadata)
    finally:
        writer.close()
    _exchange(staging / str(step), folder / str(step))
    shutil.rmtree(staging)
    mngr.reload()


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> None:
    """Swap two directories atomically (Linux renameat2); where the system cannot, `b` is moved aside
    and `a` put in its place, and `a` then holds the old `b` either way."""
    renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if renameat2 is not None:
        if renameat2(_AT_FDCWD, bytes(a), _AT_FDCWD, bytes(b), _RENAME_EXCHANGE) == 0:
            return
        if ctypes.get_errno() not in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
            raise OSError(ctypes.get_errno(), f"cannot exchange {a} and {b}")
    aside = b.with_name(f".{b.name}-replaced")
    shutil.rmtree(aside, ignore_errors=True)
    b.rename(aside)
    a.rename(b)
    aside.rename(a)


def _save(mngr: ocp.CheckpointManager, step: int, state: Any, metadata: dict) -> None:
    mngr.save(
        step,
        args=ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(metadata)),
        force=True,
    )
    mngr.wait_until_finished()


# How long a failed restore waits for its other reads to end before it cancels them.
_DRAIN_SECONDS = 30.0


class _DrainingLoop(asyncio.SelectorEventLoop):
    """An event loop that, when closed with tasks still running, first lets them end.

    Orbax runs a restore in a fresh loop and closes it as soon as one read fails, while TensorStore
    goes on with the others: their completions then land on a closed loop ("RuntimeError: Event loop
    is closed", printed from TensorStore's threads) and their coroutines, collected unfinished, print a
    traceback each with a TensorStore spec dump. A damaged checkpoint would bury the one error line
    under hundreds of lines; letting the reads end while the loop is open leaves nothing to print."""

    def close(self) -> None:
        if not self.is_closed() and not self.is_running():
            pending = asyncio.all_tasks(self)
            if pending:
                _, late = self.run_until_complete(asyncio.wait(pending, timeout=_DRAIN_SECONDS))
                for task in late:
                    task.cancel()
                if late:
                    self.run_until_complete(asyncio.wait(late, timeout=_DRAIN_SECONDS))
                for task in pending:
                    # Retrieved, so asyncio does not log each one as "never retrieved" when it is freed.
                    if task.done() and not task.cancelled():
                        task.exception()
        super().close()


class _DrainingPolicy(asyncio.DefaultEventLoopPolicy):
    def new_event_loop(self) -> asyncio.AbstractEventLoop:
        return _DrainingLoop()


@contextlib.contextmanager
def _quiet_restore() -> Iterator[None]:
    """Orbax's loops drain before they close (`_DrainingLoop`), and its warnings about what it cannot
    read stay unprinted: a restore either succeeds or raises, and the caller reports the error once."""
    loggers = [logging.getLogger(name) for name in ("absl", "orbax")]
    levels = [logger.level for logger in loggers]
    policy = asyncio.get_event_loop_policy()
    asyncio.set_event_loop_policy(_DrainingPolicy())
    for logger in loggers:
        logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        asyncio.set_event_loop_policy(policy)
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


# What TensorStore adds to its own words: the spec it was opening, each driver it went through, and the
# database's folder, which the message names already.
_TENSORSTORE_NOISE = (
    re.compile(r" \[tensorstore_spec.*$"),
    re.compile(r'Error opening "\w+" driver: '),
    re.compile(r' in OCDBT database at local file "[^"]*"'),
)


def _root_cause(exc: BaseException, step_dir: Path) -> str:
    """The innermost error behind `exc`, in short: orbax wraps TensorStore's own words (such as
    "DATA_LOSS: Error reading ...") in a message that dumps the whole TensorStore spec."""
    seen: set[int] = set()
    while id(exc) not in seen:
        seen.add(id(exc))
        inner = exc.__cause__ or exc.__context__
        if inner is None:
            break
        exc = inner
    text = str(exc).strip()
    text = text.splitlines()[0] if text else type(exc).__name__
    for noise in _TENSORSTORE_NOISE:
        text = noise.sub("", text)
    text = text.replace(f"{step_dir.absolute()}/", "")
    return text if len(text) <= 300 else text[:297] + "..."


def write_state(path: Path, state: Any) -> None:
    """`state` alone (no metadata item, no manager) in the folder `path`, waiting until it is written."""
    with contextlib.closing(ocp.StandardCheckpointer()) as saver:
        saver.save(path.absolute(), state)
        saver.wait_until_finished()


def restore_like(step_dir: Path, template: Any, *, partial: bool = False) -> Any:
    """The state saved in `step_dir`, with the structure, shapes and dtypes of `template` (arrays or
    `jax.eval_shape` structs), placed on this host's default device (so a GPU-trained checkpoint loads on
    a CPU-only machine). With `partial`, `template` may name a subtree of what was saved, such as
    {"params": ...}: only that is read."""
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    abstract = jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device), template
    )
    path = (step_dir / "state").absolute()
    try:
        with _quiet_restore():
            if partial:
                args = ocp.args.PyTreeRestore(
                    item=abstract,
                    partial_restore=True,
                    restore_args=ocp.checkpoint_utils.construct_restore_args(abstract),
                )
                with contextlib.closing(ocp.PyTreeCheckpointer()) as checkpointer:
                    return checkpointer.restore(path, args=args)
            with contextlib.closing(ocp.StandardCheckpointer()) as standard:
                return standard.restore(path, abstract)
    except Exception as exc:  # orbax raises many kinds of errors for damaged files
        raise RLLockError(
            f"checkpoint {step_dir} is corrupted or unreadable: {_root_cause(exc, step_dir)}"
        ) from None

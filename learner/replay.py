"""A replay buffer of self-play transitions, bounded in transitions, stored as compact arrays.

A multi-task run's buffer (`store_canvas` set) holds canvas states (`rllock.search.canvas`) played on
several canvases, each stored on the largest; a batch comes from one canvas, cropped to it, so that the
learner sees each state as it was played. The canvas of a batch is that of one transition drawn
uniformly: over many batches, every transition is as likely to be drawn as with one canvas.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rllock.errors import RLLockError
from rllock.process import peak_rss_mb
from rllock.search.base import BufferCounts, Episode
from rllock.search.canvas import crop_canvas


class ReplayBuffer:
    """A ring buffer: the oldest transitions are overwritten once `capacity` is reached."""

    def __init__(
        self,
        capacity: int,
        n_voxels: int,
        candidates: int,
        piece_size: int,
        label_dtype: type[np.signedinteger] = np.int8,
        voxel_dtype: type[np.signedinteger] = np.int16,
        store_canvas: int | None = None,
    ):
        """Dtypes as `rllock.core.env.compact_dtypes(task)` gives them: int8 labels, int16 voxel numbers
        for K <= 127 and N <= 32767. `store_canvas`: a multi-task run's largest canvas side (n_voxels is
        its cube)."""
        self.capacity = capacity
        self.store_canvas = store_canvas
        self.labels = np.zeros((capacity, n_voxels), label_dtype)
        self.placed = np.zeros(capacity, np.int16)
        self.chunks = np.zeros((capacity, candidates, piece_size), voxel_dtype)
        self.num_valid = np.zeros(capacity, np.int16)
        self.pi = np.zeros((capacity, candidates), np.float32)
        self.z = np.zeros(capacity, np.float32)
        self.actions = np.zeros(capacity, np.int16)  # the candidate taken (on-policy methods only)
        self.success = np.zeros(capacity, bool)  # the transition's episode succeeded
        self.pieces = np.zeros(capacity, np.int16)  # K of the transition's task (multi-task runs)
        self.canvas = np.zeros(capacity, np.int16)  # the canvas it was played on (multi-task runs)
        self.size = 0
        self.cursor = 0
        self.added = 0  # transitions ever added
        self.received_bytes = 0  # the array bytes of every episode added (what self-play ships here)

    def add(self, episode: Episode, pieces: int = 0, canvas: int = 0) -> None:
        """`pieces`, `canvas`: the episode's K and the canvas side it was played on, stored for multi-task
        runs (whose buffer holds canvas states, `rllock.search.canvas`)."""
        for t in range(len(episode.z)):
            i = self.cursor
            self.labels[i] = episode.labels[t]
            self.placed[i] = episode.placed[t]
            self.chunks[i] = episode.chunks[t]
            self.num_valid[i] = episode.num_valid[t]
            self.pi[i] = episode.pi[t]
            self.z[i] = episode.z[t]
            self.actions[i] = episode.actions[t]
            self.success[i] = episode.success
            self.pieces[i] = pieces
            self.canvas[i] = canvas
            self.cursor = (i + 1) % self.capacity
            self.size = min(self.size + 1, self.capacity)
            self.added += 1

    def add_many(self, episodes: list[Episode], pieces: int = 0, canvas: int = 0) -> BufferCounts:
        """Add a self-play batch; returns the counts after it."""
        for episode in episodes:
            self.add(episode, pieces, canvas)
            self.received_bytes += sum(
                getattr(episode, name).nbytes
                for name in ("labels", "placed", "chunks", "num_valid", "pi", "z", "actions")
            )
        return self.counts()

    def sample(self, batch: int, seed: int, success_fraction: float = 0.0) -> dict[str, np.ndarray]:
        """`batch` transitions drawn uniformly (from one canvas: module docstring), except that
        round(success_fraction * batch) of them come from successful episodes while the buffer holds
        any. A multi-task buffer's batch also says its canvas side ("canvas", an int array)."""
        rng = np.random.default_rng(seed)
        if self.store_canvas is None:
            pool = np.arange(self.size)
        else:
            side = self.canvas[rng.integers(0, self.size)]
            pool = np.flatnonzero(self.canvas[: self.size] == side)
        idx = pool[rng.integers(0, len(pool), size=batch)]
        wins = pool[self.success[pool]] if success_fraction > 0 else ()
        if len(wins):
            k = int(round(success_fraction * batch))
            idx[:k] = wins[rng.integers(0, len(wins), size=k)]
        sample = {
            "labels": self.labels[idx],
            "placed": self.placed[idx],
            "chunks": self.chunks[idx],
            "num_valid": self.num_valid[idx],
            "pi": self.pi[idx],
            "z": self.z[idx],
            "actions": self.actions[idx],
            "pieces": self.pieces[idx],
        }
        if self.store_canvas is None:
            return sample
        return {**crop_canvas(sample, self.store_canvas, int(side)), "canvas": np.array(int(side))}

    def __len__(self) -> int:
        return self.size

    _ARRAYS = ("labels", "placed", "chunks", "num_valid", "pi", "z", "actions", "success", "pieces", "canvas")

    def snapshot(self, path: str) -> None:
        """Write the buffer to `path` atomically (a temporary file renamed over it)."""
        tmp = Path(path).with_suffix(".tmp.npz")
        np.savez(
            tmp,
            size=self.size,
            cursor=self.cursor,
            added=self.added,
            **{name: getattr(self, name)[: self.size] for name in self._ARRAYS},
        )
        os.replace(tmp, path)

    def restore(self, path: str) -> int:
        """Load a snapshot written by `snapshot` (same capacity or larger); returns its size."""
        with np.load(path) as data:
            size = int(data["size"])
            if size > self.capacity:
                raise RLLockError(
                    f"replay snapshot {path} holds {size} transitions, more than --buffer-capacity "
                    f"{self.capacity}"
                )
            if self.store_canvas is not None and data["labels"].shape[1:] != self.labels.shape[1:]:
                raise RLLockError(
                    f"replay snapshot {path} holds states of another canvas than the run's "
                    f"{self.store_canvas}^3: resume with the task list it was made with"
                )
            for name in self._ARRAYS:
                if name in data:  # snapshots from before a field existed leave it at its default
                    getattr(self, name)[:size] = data[name]
            if "canvas" not in data and self.store_canvas is not None:
                self.canvas[:size] = self.store_canvas  # from before several canvases: all on one
            self.size, self.added = size, int(data["added"])
            self.cursor = int(data["cursor"]) % self.capacity
        return size

    def counts(self) -> BufferCounts:
        return BufferCounts(
            self.size, self.added, int(self.success[: self.size].sum()), self.received_bytes, peak_rss_mb()
        )

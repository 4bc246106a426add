"""A replay buffer of self-play transitions, bounded in transitions, stored as compact arrays."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rllock.errors import RLLockError
from rllock.process import peak_rss_mb
from rllock.search.base import Episode


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
    ):
        """Dtypes as `rllock.core.env.compact_dtypes(task)` gives them: int8 labels, int16 voxel numbers
        for K <= 127 and N <= 32767."""
        self.capacity = capacity
        self.labels = np.zeros((capacity, n_voxels), label_dtype)
        self.placed = np.zeros(capacity, np.int16)
        self.chunks = np.zeros((capacity, candidates, piece_size), voxel_dtype)
        self.num_valid = np.zeros(capacity, np.int16)
        self.pi = np.zeros((capacity, candidates), np.float32)
        self.z = np.zeros(capacity, np.float32)
        self.actions = np.zeros(capacity, np.int16)  # the candidate taken (on-policy methods only)
        self.success = np.zeros(capacity, bool)  # the transition's episode succeeded
        self.pieces = np.zeros(capacity, np.int16)  # K of the transition's task (multi-task runs)
        self.size = 0
        self.cursor = 0
        self.added = 0  # transitions ever added

    def add(self, episode: Episode, pieces: int = 0) -> None:
        """`pieces`: the episode's K, stored for multi-task runs (whose buffer holds canvas states,
        `rllock.search.canvas`)."""
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
            self.cursor = (i + 1) % self.capacity
            self.size = min(self.size + 1, self.capacity)
            self.added += 1

    def add_many(self, episodes: list[Episode], pieces: int = 0) -> None:
        for episode in episodes:
            self.add(episode, pieces)

    def sample(self, batch: int, seed: int, success_fraction: float = 0.0) -> dict[str, np.ndarray]:
        """`batch` transitions drawn uniformly, except that round(success_fraction * batch) of them come
        from successful episodes while the buffer holds any."""
        rng = np.random.default_rng(seed)
        idx = rng.integers(0, self.size, size=batch)
        wins = np.flatnonzero(self.success[: self.size]) if success_fraction > 0 else ()
        if len(wins):
            k = int(round(success_fraction * batch))
            idx[:k] = wins[rng.integers(0, len(wins), size=k)]
        return {
            "labels": self.labels[idx],
            "placed": self.placed[idx],
            "chunks": self.chunks[idx],
            "num_valid": self.num_valid[idx],
            "pi": self.pi[idx],
            "z": self.z[idx],
            "actions": self.actions[idx],
            "pieces": self.pieces[idx],
        }

    def __len__(self) -> int:
        return self.size

    _ARRAYS = ("labels", "placed", "chunks", "num_valid", "pi", "z", "actions", "success", "pieces")

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
            for name in self._ARRAYS:
                if name in data:  # snapshots from before a field existed leave it at its default
                    getattr(self, name)[:size] = data[name]
            self.size, self.added = size, int(data["added"])
            self.cursor = int(data["cursor"]) % self.capacity
        return size

    def stats(self) -> dict[str, float]:
        return {
            "size": self.size,
            "added": self.added,
            "successes": int(self.success[: self.size].sum()),
            "capacity": self.capacity,
            "peak_rss_mb": peak_rss_mb(),
        }

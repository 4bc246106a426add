"""What a training run plays and learns from: one contract for a single task and for many.

A run's `Workload` draws the task of each self-play batch, names the fixed tasks of every validation,
says what the replay buffer stores and turns a stored batch into the network's inputs. Callers never
ask which kind they hold (pgx's `core.Env` is the model):
- `SingleTask`: the paper's setting. Every batch plays the one task; the buffer stores its states as
  they are (labels per shape voxel) and the learner maps them through the shape's own symmetries.
- `ManyTasks`: `rllock train --tasks` (`rllock.core.tasks`). Every batch draws a task group; the buffer
  stores canvas states on the largest canvas (`rllock.search.canvas`) and the learner maps them through
  their bounding box's 48 maps.
Both are plain data, so that they travel to Ray actors; a task is built where it is played.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import Task, compact_dtypes, make_task
from rllock.core.identity import task_identity
from rllock.core.tasks import TaskSet
from rllock.core.topology import symmetries
from rllock.search.base import Episode
from rllock.search.canvas import augment_canvas, canvas_episode
from rllock.search.methods import space
from rllock.search.network import canvas_index, encode_batch, encode_canvas


@dataclass(frozen=True)
class Draw:
    """A task to play, on the canvas it is played on; `group` is its task group as numbered and `label`
    as written in --tasks (-1 and None: a single task)."""

    group: int
    task: Task
    canvas: int
    label: str | None = None


@dataclass(frozen=True)
class BufferLayout:
    """The replay buffer's transition shape (states, candidates, piece size), its label and voxel dtypes,
    and the canvas its states are stored on (None: a single task's own voxels)."""

    shape: tuple[int, int, int]
    dtypes: tuple[type[np.signedinteger], type[np.signedinteger]]
    store_canvas: int | None


class Workload(ABC):
    """What a run plays (module docstring)."""

    @property
    @abstractmethod
    def canvas(self) -> int:
        """The canvas a checkpoint of the run plays on (the smallest of its canvases)."""

    @abstractmethod
    def identity(self) -> dict:
        """What a checkpoint of the run is for (its metadata's task)."""

    @abstractmethod
    def describe(self) -> str:
        """The run's task in words, for the log."""

    @abstractmethod
    def draw(self, rng: np.random.Generator) -> Draw:
        """The task of the next self-play batch."""

    @abstractmethod
    def validation(self, seed: int) -> list[Draw]:
        """The tasks every validation plays: the same for the same seed."""

    @abstractmethod
    def stored(self, draw: Draw, episodes: list[Episode]) -> list[Episode]:
        """Played episodes of `draw`, as the replay buffer stores them."""

    @abstractmethod
    def buffer_layout(self, method: str, mcts: MCTSConfig) -> BufferLayout: ...

    @abstractmethod
    def inputs(
        self, sample: dict[str, np.ndarray], net: NetConfig, seed: int | None
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """(planes, candidates as canvas indices, the sample as learned from) of a replay batch; with a
        `seed`, each transition is first mapped through a random symmetry."""


@dataclass(frozen=True, eq=False)
class SingleTask(Workload):
    """One task (module docstring), on `side`^3."""

    grid: np.ndarray
    pieces: int
    removal: str
    name: str
    side: int

    @staticmethod
    def of(task: Task, canvas: int) -> SingleTask:
        return SingleTask(task.topology.grid, task.pieces, task.removal, task.shape_name, canvas)

    def __reduce__(self):  # the task and its tables are built again where it lands
        return SingleTask, (self.grid, self.pieces, self.removal, self.name, self.side)

    @functools.cached_property
    def task(self) -> Task:
        return make_task(self.grid, self.pieces, self.removal, name=self.name)

    @functools.cached_property
    def _symmetries(self) -> np.ndarray:
        return symmetries(self.task.topology)

    @property
    def canvas(self) -> int:
        return self.side

    def identity(self) -> dict:
        return task_identity(self.task, self.side)

    def describe(self) -> str:
        return f"{self.name} K={self.pieces}"

    def draw(self, rng: np.random.Generator) -> Draw:
        return Draw(-1, self.task, self.side)

    def validation(self, seed: int) -> list[Draw]:
        return [Draw(-1, self.task, self.side)]

    def stored(self, draw: Draw, episodes: list[Episode]) -> list[Episode]:
        return episodes

    def buffer_layout(self, method: str, mcts: MCTSConfig) -> BufferLayout:
        m, n = space(method).action_shape(self.task, mcts)
        return BufferLayout((self.task.size, m, n), compact_dtypes(self.task), None)

    def inputs(self, sample, net, seed):
        if seed is not None:
            sample = augment(sample, self._symmetries, seed)
        planes = encode_batch(self.task, sample["labels"], sample["placed"], self.side, net.task_planes)
        chunks = canvas_index(self.task, self.side)[sample["chunks"].astype(np.int64)]
        return planes, chunks, sample


@dataclass(frozen=True, eq=False)
class ManyTasks(Workload):
    """Task groups, each on its canvas (module docstring)."""

    tasks: TaskSet

    @property
    def canvas(self) -> int:
        return self.tasks.canvas

    def identity(self) -> dict:
        return self.tasks.identity()

    def describe(self) -> str:
        return f"tasks {self.tasks.spec}"

    def draw(self, rng: np.random.Generator) -> Draw:
        group, task = self.tasks.draw(rng)
        return Draw(group, task, self.tasks.groups[group].canvas, self.tasks.groups[group].spec)

    def validation(self, seed: int) -> list[Draw]:
        chosen = self.tasks.validation_tasks(seed)
        groups = enumerate(zip(chosen, self.tasks.groups))
        return [Draw(g, task, group.canvas, group.spec) for g, (task, group) in groups]

    def stored(self, draw: Draw, episodes: list[Episode]) -> list[Episode]:
        store, n_max = self.tasks.store_canvas, self.tasks.max_piece_size()
        return [canvas_episode(draw.task, e, store, n_max) for e in episodes]

    def buffer_layout(self, method: str, mcts: MCTSConfig) -> BufferLayout:
        store = self.tasks.store_canvas
        return BufferLayout(
            (store**3, mcts.candidates, self.tasks.max_piece_size()), (np.int8, np.int16), store
        )

    def inputs(self, sample, net, seed):
        canvas = int(sample.get("canvas", self.canvas))  # the batch's own canvas (rllock.learner.replay)
        if seed is not None:
            sample = augment_canvas(sample, canvas, seed)
        planes = encode_canvas(sample["labels"], sample["placed"], sample["pieces"], canvas, net.task_planes)
        return planes, sample["chunks"].astype(np.int32), sample


def augment(sample: dict[str, np.ndarray], perms: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """Each transition mapped through one of the voxel permutations `perms` [S, N], drawn uniformly:
    a symmetric image of a state, with the same candidates (mapped), search policy and value."""
    rows = perms[np.random.default_rng(seed).integers(0, len(perms), size=len(sample["labels"]))]
    labels = np.empty_like(sample["labels"])
    np.put_along_axis(labels, rows, sample["labels"], axis=1)  # labels'[p(v)] = labels[v]
    chunks = np.take_along_axis(rows, sample["chunks"].reshape(len(rows), -1).astype(np.int64), axis=1)
    return {
        **sample,
        "labels": labels,
        "chunks": chunks.reshape(sample["chunks"].shape).astype(sample["chunks"].dtype),
    }

"""The paper's search with its network evaluated elsewhere: in a model server that batches the evaluations
of many searches into one network call (`rllock serve`'s model deployment).

The tree search is the same compiled mctx program as `rllock.search.mcts`; only the network call inside
it becomes a host callback to `evaluate(planes) -> (voxel logits [B, C^3], value [B])`. The search's
parameters are then an empty tree: the weights live with the evaluator.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import Task
from rllock.errors import RLLockError
from rllock.search.mcts import CompiledSearch, Searcher
from rllock.search.methods import space
from rllock.search.network import PolicyValueNet, chunk_logits

Evaluate = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""planes [B, C, C, C, P] (float32) -> (voxel logits [B, C^3], value [B]), both float32."""


class RemoteSearch(CompiledSearch):
    """A `CompiledSearch` whose network runs in `evaluate` (on the host, outside the compiled program)."""

    def __init__(
        self, evaluate: Evaluate, net: NetConfig, config: MCTSConfig, task: Task, batch: int, method: str
    ):
        if method != "rl-lock":
            raise RLLockError(f"a remote network serves the rl-lock method only, not {method!r}")
        super().__init__(PolicyValueNet(net), config, space(method), task, batch)
        self.evaluate = evaluate

    def _host_evaluate(self, planes) -> tuple[np.ndarray, np.ndarray]:
        logits, value = self.evaluate(np.asarray(planes, np.float32))
        return np.asarray(logits, np.float32), np.asarray(value, np.float32)

    def _evaluate(self, params, planes, chunks, valid):
        del params
        rows = planes.shape[0]
        shapes = (
            jax.ShapeDtypeStruct((rows, self.canvas**3), jnp.float32),
            jax.ShapeDtypeStruct((rows,), jnp.float32),
        )
        voxel_logits, value = io_callback(self._host_evaluate, shapes, planes)
        return chunk_logits(voxel_logits, chunks, valid), value


def remote_searcher(compiled: RemoteSearch, task: Task) -> Searcher:
    """One lockstep group through `compiled` for `task` (a task of the same piece size and candidates:
    the compiled program depends on the shapes only); play it with empty parameters ({})."""
    return Searcher(compiled.net, compiled.config, compiled.space, task, compiled.batch, compiled)

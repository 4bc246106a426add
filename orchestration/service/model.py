"""The model deployment of `rllock serve`: checkpoints loaded by name once, and every network evaluation
of every job through one batched call (`@serve.batch`): the searches of concurrent jobs send their
states here, and those that arrive together are evaluated together.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
from ray import serve

from rllock.core.env import Task

MAX_BATCH_REQUESTS = 32
BATCH_WAIT_S = 0.002  # what a lone request waits for company: small beside a simulation's host time


def _bucket(rows: int) -> int:
    """Rows padded to a power of two, so that the network compiles for a few batch sizes only."""
    return 1 << max(rows - 1, 0).bit_length()


class ModelServer:
    """Policies by (checkpoint, canvas), and counts of the batches evaluated (`stats`)."""

    def __init__(self) -> None:
        self._nets: dict[str, tuple] = {}
        self._lock = threading.Lock()
        self._calls = self._requests = self._states = 0
        self._sizes: dict[int, int] = {}

    def describe(self, checkpoint: str, task: Task):
        """(the key to evaluate with, the checkpoint's policy for `task` without its weights)."""
        import jax

        from rllock.search.inference import load_policy
        from rllock.search.network import PolicyValueNet

        policy = load_policy(checkpoint, task)
        key = f"{checkpoint}@{policy.net.canvas}"
        with self._lock:
            if key not in self._nets:
                self._nets[key] = (jax.jit(PolicyValueNet(policy.net).apply), policy.params)
        return key, dataclasses.replace(policy, params={})

    @serve.batch(max_batch_size=MAX_BATCH_REQUESTS, batch_wait_timeout_s=BATCH_WAIT_S)
    async def evaluate(self, requests: list[tuple[str, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(voxel logits, value) for each request's states (key, planes [B, C, C, C, P]); the requests
        of one network are evaluated in one call."""
        out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(requests)
        for key in dict.fromkeys(k for k, _ in requests):
            idx = [i for i, (k, _) in enumerate(requests) if k == key]
            planes = np.concatenate([requests[i][1] for i in idx])
            rows = planes.shape[0]
            padded = np.zeros((_bucket(rows), *planes.shape[1:]), np.float32)
            padded[:rows] = planes
            apply, params = self._nets[key]
            logits, value = apply({"params": params}, padded)
            logits, value = np.asarray(logits)[:rows], np.asarray(value)[:rows]
            at = 0
            for i in idx:
                b = requests[i][1].shape[0]
                out[i] = (logits[at : at + b], value[at : at + b])
                at += b
            self._count(len(idx), rows)
        return out  # type: ignore[return-value]

    def _count(self, requests: int, states: int) -> None:
        self._calls += 1
        self._requests += requests
        self._states += states
        self._sizes[requests] = self._sizes.get(requests, 0) + 1

    def stats(self) -> dict:
        """Network calls, the requests and states they evaluated, the mean requests per call, and how
        many calls had each number of requests."""
        calls = max(self._calls, 1)
        return {
            "calls": self._calls,
            "requests": self._requests,
            "states": self._states,
            "mean_requests_per_call": self._requests / calls,
            "mean_states_per_call": self._states / calls,
            "requests_per_call": {str(k): v for k, v in sorted(self._sizes.items())},
            "networks": sorted(self._nets),
        }

"""Ray start-up, the self-play layout (how many actors, threads and episodes each), and a pool of
self-play actors with exactly one batch in flight per actor, shared by the trainer and the bench."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import ray
from ray.exceptions import RayActorError

from actors.selfplay import PlayStats, SelfPlayActor, TaskSpec, actor_env
from rllock.config import MCTSConfig, NetConfig, SelfPlayConfig

log = logging.getLogger(__name__)


def start_ray(address: str | None) -> bool:
    """Connect to Ray; True when this process started the instance (and so must shut it down)."""
    if ray.is_initialized():
        return False
    if address:
        ray.init(address=address, logging_level=logging.WARNING)
    else:
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, logging_level=logging.WARNING)
    return True


@dataclass(frozen=True)
class Layout:
    """How self-play runs: `actors` Ray actors, each with `episodes` lockstep episodes, `cpus` Ray CPUs,
    `threads` sampler threads and `gpus` Ray GPUs."""

    actors: int
    episodes: int
    cpus: float
    threads: int
    groups: int  # lockstep groups per actor, searched in threads of their own
    gpus: float
    mode: str  # "per-actor" or "lockstep"


def plan_layout(selfplay: SelfPlayConfig, *, cpus: float, gpus: float, reserved_cpus: float) -> Layout:
    """The layout for a cluster with `cpus` and `gpus` (`reserved_cpus` stay for the learner).

    per-actor: `actors` actors (default one per free core), each on its share of the free cores, with one
    lockstep group per core. lockstep: one worker that plays all the actors' episodes in one lockstep
    batch, with the network on the GPU when there is one and the sampler spread over the free cores."""
    free = max(1.0, cpus - reserved_cpus)
    actors = selfplay.actors or max(1, int(free))
    mode = selfplay.evaluation
    if mode == "auto":
        mode = "lockstep" if gpus > 0 else "per-actor"
    if mode == "lockstep":
        gpu = 1.0 if gpus > 0 else 0.0
        return Layout(1, actors * selfplay.episodes_per_batch, free, max(1, int(free)), 1, gpu, mode)
    share = free / actors  # fractional when there are more actors than cores: they take turns
    threads = max(1, int(share))
    return Layout(actors, selfplay.episodes_per_batch, share, threads, threads, 0.0, mode)


class ActorPool:
    """Self-play actors, each with one batch in flight. A dead actor process is restarted by Ray and its
    call retried; the pool notices the new process and logs it. An actor that fails for good is dropped."""

    def __init__(self, spec: TaskSpec, net: NetConfig, mcts: MCTSConfig, layout: Layout, seed: int, buffer):
        options = dict(
            num_cpus=layout.cpus,
            num_gpus=layout.gpus,
            max_restarts=-1,
            max_task_retries=-1,
            runtime_env={"env_vars": actor_env(layout.threads, gpu=layout.gpus > 0)},
        )
        self.actors = [
            SelfPlayActor.options(**options).remote(
                spec, net, mcts, layout.episodes, seed + i, layout.groups, buffer
            )
            for i in range(layout.actors)
        ]
        self.pids = dict(zip(self.actors, ray.get([a.pid.remote() for a in self.actors])))
        self.inflight: dict = {}

    def submit(self, actor, weights: list, version: int) -> None:
        self.inflight[actor.run.remote(weights, version)] = (actor, version)

    def submit_all(self, weights: list, version: int) -> None:
        for actor in self.actors:
            self.submit(actor, weights, version)

    def oldest_version(self) -> int | None:
        return min((v for _, v in self.inflight.values()), default=None)

    def collect(self, timeout: float) -> list[tuple[object, PlayStats]]:
        """The batches finished within `timeout` seconds (at most one wait), with their actors."""
        ready, _ = ray.wait(list(self.inflight), num_returns=1, timeout=timeout)
        done = []
        for ref in ready:
            actor, _ = self.inflight.pop(ref)
            try:
                stats = ray.get(ref)
            except RayActorError as exc:  # restarts exhausted or the node is gone: go on without it
                log.error("a self-play actor failed for good: %s", str(exc).splitlines()[0])
                continue
            if self.pids[actor] != stats.pid:
                log.warning("self-play actor restarted (pid %d -> %d)", self.pids[actor], stats.pid)
                self.pids[actor] = stats.pid
            done.append((actor, stats))
        return done

    def alive(self) -> bool:
        return bool(self.inflight)

    def shutdown(self) -> None:
        """Stop every actor now; batches in flight are dropped."""
        for actor in self.actors:
            ray.kill(actor)
        self.inflight.clear()

"""The learner: a pure jitted update step inside a thin stateful class (acme style)."""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
import optax

from rllock.config import LearnerConfig
from rllock.search.network import NetConfig, PolicyValueNet, chunk_logits, init_params
from rllock.search.ppo import ppo_loss
from rllock.search.workload import Workload


def loss_fn(params, net: PolicyValueNet, planes, chunks, valid, pi, z):
    """Cross-entropy(pi, p) + (z - v)^2, averaged over the batch; also returns both terms."""
    voxel_logits, value = net.apply({"params": params}, planes)
    logits = chunk_logits(voxel_logits, chunks, valid)
    log_p = jax.nn.log_softmax(logits, axis=-1)
    policy = -jnp.sum(jnp.where(valid, pi * log_p, 0.0), axis=-1).mean()
    value_loss = jnp.mean((z - value) ** 2)
    return policy + value_loss, (policy, value_loss)


@partial(jax.jit, static_argnames=("net", "optimizer"))
def update_step(params, opt_state, batch, *, net: PolicyValueNet, optimizer: optax.GradientTransformation):
    """One step on the search methods' loss; batch = (planes, chunks, valid, pi, z)."""
    grads, (policy, value_loss) = jax.grad(loss_fn, has_aux=True)(params, net, *batch)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, policy, value_loss


@partial(jax.jit, static_argnames=("net", "optimizer", "config"))
def ppo_update_step(
    params, opt_state, batch, *, net: PolicyValueNet, optimizer: optax.GradientTransformation, config
):
    """One step on PPO's loss (`rllock.search.ppo.ppo_loss`); batch = (planes, chunks, valid, behaviour pi,
    actions, z)."""
    loss = partial(
        ppo_loss, clip=config.clip_ratio, value_coef=config.value_coef, entropy_coef=config.entropy_coef
    )
    grads, (policy, value_loss, _) = jax.grad(loss, has_aux=True)(params, net, *batch)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, policy, value_loss


@lru_cache(maxsize=32)
def adam(learning_rate: float) -> optax.GradientTransformation:
    """One Adam per learning rate in a process: the jitted steps take the optimizer as a static argument,
    so a new one for each learner would trace and compile the same step again."""
    return optax.adam(learning_rate)


class AdamState:
    """Parameters, Adam's state, the learner step and the PRNG key: everything a resume needs, and the
    seeds of the replay samples. `key` is a raw uint32[2] PRNG key (jax.random.PRNGKey), kept raw so
    that checkpoints store it as is; `init` makes the parameters from a key split off it."""

    def __init__(self, init: Callable[[jax.Array], dict], learning_rate: float, key: jax.Array):
        self.optimizer = adam(learning_rate)
        init_key, self.key = jax.random.split(key)
        self.params = init(init_key)
        self.opt_state = self.optimizer.init(self.params)
        self.step = 0

    def start_from(self, params) -> None:
        """Fine-tuning: these parameters (another run's network of the same architecture), with a fresh
        optimizer."""
        self.params = params
        self.opt_state = self.optimizer.init(params)

    @property
    def weights(self) -> dict:
        """The parameters the actors act with."""
        return self.params

    def next_seed(self) -> int:
        """A seed for the next replay sample, from the learner's PRNG key (saved with checkpoints, so a
        resumed run draws the same mini-batches it would have drawn)."""
        self.key, sub = jax.random.split(self.key)
        return int(jax.random.randint(sub, (), 0, np.iinfo(np.int32).max))

    def state(self) -> dict:
        """Everything a resume needs, as one pytree."""
        return {
            "params": self.params,
            "opt_state": self.opt_state,
            "step": np.asarray(self.step, dtype=np.int64),
            "key": np.asarray(self.key),
        }

    def load_state(self, state: dict) -> None:
        self.params = state["params"]
        self.opt_state = state["opt_state"]
        self.step = int(state["step"])
        self.key = jnp.asarray(state["key"], jnp.uint32)


class Learner(AdamState):
    def __init__(
        self,
        workload: Workload,
        net_config: NetConfig,
        config: LearnerConfig,
        key: jax.Array,
        method: str = "rl-lock",
    ):
        """`method`: ppo learns with PPO's loss, the search methods with cross-entropy and value error.
        `workload`: what the run plays, which says how its stored states become network inputs."""
        super().__init__(partial(init_params, net_config), config.learning_rate, key)
        self.workload = workload
        self.ppo = method == "ppo"
        self.net = PolicyValueNet(net_config)
        self.net_config = net_config
        self.config = config

    def prepare(self, sample: dict[str, np.ndarray], seed: int | None = None) -> tuple:
        """Replay-buffer arrays -> network inputs (planes, candidate canvas indices, mask, pi, z; for PPO
        pi, actions, z). With a `seed` (and symmetries on), each transition is first mapped through a
        random symmetry."""
        seed = seed if self.config.symmetries else None
        planes, chunks, sample = self.workload.inputs(sample, self.net_config, seed)
        m = sample["chunks"].shape[1]
        valid = np.arange(m)[None, :] < sample["num_valid"][:, None]
        if self.ppo:
            return planes, chunks, valid, sample["pi"], sample["actions"].astype(np.int32), sample["z"]
        return planes, chunks, valid, sample["pi"], sample["z"]

    def update(self, sample: dict[str, np.ndarray]) -> dict[str, float]:
        batch = self.prepare(sample, self.next_seed())
        if self.ppo:
            self.params, self.opt_state, policy, value_loss = ppo_update_step(
                self.params, self.opt_state, batch, net=self.net, optimizer=self.optimizer, config=self.config
            )
        else:
            self.params, self.opt_state, policy, value_loss = update_step(
                self.params, self.opt_state, batch, net=self.net, optimizer=self.optimizer
            )
        self.step += 1
        return {"policy": float(policy), "value": float(value_loss)}

    def learn(self, sample: dict[str, np.ndarray]) -> dict[str, float]:
        """One step (`update`); returns its losses by TensorBoard tag."""
        losses = self.update(sample)
        policy, value = losses["policy"], losses["value"]
        return {"losses/policy": policy, "losses/value": value, "losses/total": policy + value}

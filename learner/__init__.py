"""The JAX learner: replay buffer, update step, checkpoints and TensorBoard logging."""

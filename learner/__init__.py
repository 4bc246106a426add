"""The JAX learners, imported as `rllock.learner`: the policy-value learner and the guide's learner, their
replay buffers, update steps and snapshots."""

"""The actors, imported as `rllock.actors`: self-play episodes and guide searches as plain worker logic,
and the Ray actors that run them, each on one CPU core."""

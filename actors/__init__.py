"""Self-play: plain worker logic, and the Ray actor that runs it on one CPU core."""

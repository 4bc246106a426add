"""The files layer: what RL-Lock reads and writes, built on the core.

  assembly.py     assembly.json and .puz: written only after the full verifier passes
  checkpoint.py   orbax checkpoints, their typed metadata, shipped names, and a run's saved config
  export.py       STL/OBJ/3MF meshes and BurrTools .xmpuzzle
  render.py       pictures, animations and the self-contained HTML viewer

Nothing here imports `rllock.search` or the packages above `rllock`.
"""

"""The search layer: the network and every search that builds assemblies, on the core and the files.

  base.py           the contract types the searches, actors and learner share (Episode, Player, TimeSplit)
  network.py        the policy-value 3D U-Net and the state encoding
  canvas.py         states on the canvas, and the symmetries of mini-batches of many shapes
  nodes.py          the search tree's node store (states, candidates, children), its features and episodes
  mcts.py           MCTS over whole pieces (mctx's Gumbel MuZero, expanded by the compiled sampler)
  voxel_search.py   MCTS over single voxels (RL-Lock_Action)
  ppo.py            the PPO baseline's policy player and loss
  methods.py        the three training methods and their defaults
  solver.py         randomized depth-first search with restarts: no training needed
  inference.py      checkpoints to policies, and the paper's generation protocol
  pretrained.py     the checkpoints shipped inside the package, by name

Nothing here imports `actors`, `learner` or `orchestration`.
"""

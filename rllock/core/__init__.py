"""The core layer: what an interlocking assembly is, with no learning and no files.

  shapes.py                 voxel shapes: built-in names, .puz/.vol/.npy files, meshes, bounds, fingerprints
  mesh_files.py             triangles from mesh files: STL, OBJ, PLY (strips too), OFF, glTF/GLB, 3MF
  meshes.py                 mesh models to voxel shapes (input)
  piece_meshes.py           pieces to watertight meshes (export)
  topology.py               a shape's neighbour and ray tables, and its symmetries
  reference_checkers.py     the three checks and the sampler written plainly, the verifier's ground truth
  compiled_checkers.py      the same checks compiled (numba), incremental per search node
  compiled_interlocking.py  the compiled interlocking check and the contact graph it reads
  compiled_proposals.py     how the compiled sampler grows raw chunks: frontier and closed proposals
  compiled_sampler.py       the compiled chunk sampler and the candidates of search nodes
  env.py                    the environment: a task, a state, candidates, a step (pure functions)
  voxel_env.py              the voxel-level environment of the paper's section 3 (the baselines)
  verifier.py               the full verifier over every stage of an assembly
  tasks.py                  task groups and the task sets of multi-task training

Nothing here imports `rllock.files`, `rllock.search` or the packages above `rllock`.
"""

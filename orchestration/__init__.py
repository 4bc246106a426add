"""The orchestration layer: the training loop, the Ray actor pool, generation on Ray and the self-play
bench. It sits above `rllock` (the library), `actors` and `learner`, and the command line calls it.

  pacing.py    pure rules: when the learner may step, when periodic work is due, what the budget allows
  pool.py      Ray start-up and a pool of self-play actors with one batch in flight each
  recorder.py  TensorBoard, checkpoints and the best assembly of a run
  train.py     the actor-learner loop (`rllock train`)
  generate.py  the inference protocol spread over Ray actors (`rllock generate --actors N`)
  bench.py     self-play throughput (`rllock bench selfplay`)
"""

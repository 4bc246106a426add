"""The orchestration layer: the training loop, the Ray actor pool, generation on Ray, the command line and
the benches. It sits above `rllock` (the library), `actors` and `learner`.

  pacing.py      pure rules: when the learner may step, when periodic work is due, what the budget allows
  pool.py        Ray start-up and a pool of self-play actors with one batch in flight each
  recorder.py    TensorBoard, checkpoints and the best assembly of a run
  validation.py  a run's validation: its fixed tasks, playing them, the score, keeping the best checkpoint
  train.py       the actor-learner loop (`rllock train`)
  generate.py    the inference protocol spread over Ray actors (`rllock generate --actors N`)
  cli/           the `rllock` command line
  bench/         every `rllock bench` command
"""

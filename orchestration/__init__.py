"""The orchestration layer, imported as `rllock.orchestration`: the trainers, generation on Ray, the
service, the command line and the benches. It sits above the library (`rllock.core`, `.files`,
`.search`) and the actors and learners (`rllock.actors`, `rllock.learner`).

  loop.py          the one actor-learner loop both trainers run, over the parts a builder makes
  builder.py       the trainers' builders (self-play, guide, offline guide) and `run`
  train.py         `rllock train`: the self-play builder's run and what it watches (validations, charts)
  guide_train.py   `rllock train-guide`: the guide builder's run and what it watches (searches, judging)
  guide_offline.py replay snapshots of guide runs: pooled, kept apart with their record
  pacing.py        pure rules: when the learner may step, when periodic work is due, what the budget allows
  pool.py          Ray start-up and the pools of self-play and search actors, one batch in flight each
  recorder.py      the counters, TensorBoard, checkpoints and the best assembly of a run
  validation.py    a run's validation: its fixed tasks, playing them, the score, keeping the best checkpoint
  stopping.py      signals: a stop request saves a checkpoint first
  generate.py      the inference protocol spread over Ray actors (`rllock generate --actors N`)
  service/         `rllock serve`: the HTTP API, its job queue and the web page
  cli/             the `rllock` command line
  bench/           every `rllock bench` command
"""

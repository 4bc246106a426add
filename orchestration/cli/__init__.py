"""The `rllock` command line, above every layer: each module registers its own subcommands.

  main.py         the parser, logging and the one-line error handling (`rllock` itself)
  common.py       arguments that several commands share, checked output folders, checkpoint loading
  assemblies.py   verify, solve, show, export
  training.py     train, generate, pretrained
  flags.py        command-line flags generated from the typed configs

The benchmarks register under `rllock bench` from `rllock.orchestration.bench`.
"""

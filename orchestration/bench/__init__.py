"""Every `rllock bench` command, in one place.

commands.py   registers the bench subcommands and their shared protocol flags
solve.py      the compiled checkers' throughput and the solver on the paper's cube tasks
paper.py      the paper's protocol on the shipped checkpoints, beside the paper's figures
transfer.py   a multi-task checkpoint zero-shot on held-out tasks
ablation.py   the paper's Table 1 for the three methods, from training runs
learning.py   a checkpoint against the same search untrained, and success rates over many episodes
selfplay.py   self-play throughput for actor counts
"""

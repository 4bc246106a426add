"""Every `rllock bench` command, in one place.

commands.py   registers every bench subcommand and its flags (the protocol flags shared once)
entry.py      each bench's command: parse its lists, run it, print its result
specs.py      the comma-separated lists the benches take (tasks, counts, names), parsed once
arms.py       what the table benches share: an arm under the paper's protocol, timed, and its cells
solve.py      the compiled checkers' throughput and the solver on the paper's cube tasks
paper.py      the paper's protocol on the shipped checkpoints, beside the paper's figures
transfer.py   a multi-task checkpoint zero-shot on held-out tasks
ablation.py   the paper's Table 1 for the three methods, from training runs
learning.py   a checkpoint against the same search untrained, and success rates over many episodes
selfplay.py   self-play throughput for actor counts, and where the time goes
scaling.py    self-play and the learner over actor counts and Ray nodes
shapes.py     large shapes swept over K: the solver and `general`, time to the first valid assembly
"""

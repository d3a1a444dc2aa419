"""Studies: a grid of runs to a verdict, from a study file or a command line.

A study declares tasks, algorithms, strategies (each under its label, with its settings),
seeds and a budget, the metrics and the claims to judge (`spec`). Each (task, algorithm,
strategy) is a cell (`cell`): one vmapped sweep of N seeds, run as a subprocess by an
executor (`execute`; on a Ray cluster, `ray_executor`) into the study's folder, resumable,
its cost estimated (`cost`) and, before it runs, measured by probes (`plan`). A ``tune:``
block (`tune`) tunes each strategy with the same budget first, by a grid or Optuna
(`tune_run`, `optuna_search`). The finished
cells' curves go to the study's table (`curves`); the report (`report`, `stats`,
`figures`) gives rliable's intervals, the probability of improvement and a verdict per
claim. A stopped cell's state travels as one file (`carry`), and `verify` checks that the
code at HEAD still computes a finished cell bit for bit. The command is `command`
(``python -m coherent_jax.study``).
"""

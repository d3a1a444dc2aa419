"""Benchmarks: ``python -m benchmarks [SUITE] [key=value ...]``, from the repository's root.

A folder of the repository beside the package, not part of the ``coherent_jax`` wheel:
the suites import the package, and the package imports nothing of them. The ``bench``
extra (``pip install -e ".[bench]"``) adds EnvPool for the ``standard`` suite.

One module per suite, each with the same shape: ``KEYS`` (its own settings, as
`coherent_jax.config.cli.Key`s), ``parse(items)`` (every check, before any work),
``run(items, log)`` (measures, writes its JSON atomically, returns the results)
and ``format_table(result)``.

* `throughput` (the default): raw env, our trainers and Brax's PPO, env steps/s;
* `coherent`: what coherent exploration costs next to action noise (training, the
  filter against the dense reference of
  `coherent_jax.exploration.coherent.reference`, the loss's segment log-prob);
* `sac`: SAC and Coherent-SAC iterations, collection and updates apart;
* `strategies`: every exploration strategy's iteration of one algorithm, side by side;
* `physics`: MJX settings against native MuJoCo, one subprocess per row;
* `standard`: Gymnasium's tasks against their Brax re-creations and EnvPool;
* `gradient`: each coherent loss's gradient against a float64 whole-episode reference;
* `processes`: one training process with N devices against N processes of one device
  (``distributed=true`` over loopback), each a fresh ``python -m coherent_jax.train``;
* `gym`: Gymnasium envs stepped on the host (``env=gym:ID``) against Gymnasium's own
  ``SyncVectorEnv``, with where the time goes (the pool, the callback, training).
* `sbx`: our SAC beside SBX's (``sbx-rl``, the JAX Stable-Baselines) at identical settings,
  SBX in a venv of its own made on first use from ``benchmarks/sbx-requirements.txt``.
* `overlap`: a probe: the rollout and the PPO iteration with the envs stepped as K
  independent groups inside the scanned step, against one group (K = 1).

`measure` holds what every suite records (times, memory, machine, JSON). Each suite's
``COST`` says how long it took at its defaults, and where (``--help`` prints it).
"""

SUITES = (
    "throughput",
    "coherent",
    "sac",
    "strategies",
    "physics",
    "standard",
    "gradient",
    "processes",
    "gym",
    "sbx",
    "overlap",
)
# Where each suite's ``COST`` (its wall time at its defaults) was measured; idle, it takes less.
COST_MACHINE = "2026-12-06 on 2 cores of an Intel Xeon (avx512f) shared with other jobs (load average 3-12)"
DEFAULT_SUITE = "throughput"  # what ``python -m benchmarks`` runs with no suite named
# Training keys the in-process suites do not read (they time iterations: they write no run
# directory, checkpoint or TensorBoard file, and run no fixed budget): refused, not ignored.
# A suite that starts training commands of its own names its own (``IGNORED_KEYS``).
IGNORED = (
    "run_dir",
    "resume",
    "checkpoint_every",
    "tensorboard",
    "wandb",
    "wandb_init_timeout",
    "progress",
    "total_steps",
    "eval_every",
)

"""Command-line training: ``python -m coherent_jax.train env=halfcheetah algo=ppo ...``.

Overrides are ``key=value`` (``--help`` lists them all). A bad override is
reported in one line and exits with status 2 before anything is written. A run
writes one directory:

* ``config.yaml`` (resolved config) and ``versions.json`` (Python, platform, package
  versions);
* ``metrics.jsonl`` (one row per iteration, with ``eval/*`` on evaluation rows) and,
  with ``tensorboard=true``, the same scalars as TensorBoard event files in ``tb/``;
* ``checkpoint.msgpack`` (the whole train state and the loop's state, every
  ``checkpoint_every`` iterations, at the end and when stopped by SIGINT/SIGTERM;
  see `coherent_jax.run.checkpoint`);
* at the end ``params.msgpack`` (final parameters and observation statistics, flax
  serialisation) and ``summary.json``;
* with ``wandb=true``, ``wandb-run.json`` (the W&B run's id) and ``wandb/``: the same
  config, rows and summary in a Weights & Biases run (`coherent_jax.run.outputs`).

``coherent_jax.learn(config)`` (`coherent_jax.api.learn`) runs the same launch path from
Python.

``resume=RUN_DIR`` continues a run from its checkpoint (a run killed at any moment,
even by SIGKILL, from any working directory, after the directory was moved): the
rows past the checkpoint are dropped and recomputed, so the metrics equal those of
an uninterrupted run of the same seed; ``resume=RUN_DIR total_steps=N`` extends a
finished run. While it trains, a run holds ``run.lock`` in its directory
(`coherent_jax.run.rundir`): a second process starting or resuming there is refused. Before
anything is written, a key given twice, a configuration whose arrays cannot fit in
memory (`coherent_jax.run.memory`), a sweep's directory given to ``resume=`` and a run whose
``metrics.jsonl`` lost rows before its checkpoint are refused like any bad input.
A non-finite loss or parameter stops the run (exit status 3) naming
the iteration and the quantity; the last good checkpoint stays. `main` reads top down: the
mode (``--help``, a dry run or a run), then `coherent_jax.run.launch.launch_train` (parse,
check, prepare the run directory, train, exit status). The helpers it shares with sweeps
are `coherent_jax.run.launch`'s, the loop is `coherent_jax.run.loop`'s. Exit statuses
(`coherent_jax.exit_codes`): 0 done, 2 bad input, 3 diverged, 4 another process of a
``distributed=true`` run failed (resumable; see `coherent_jax.run.multihost`), 128 +
signal number when stopped by SIGINT/SIGTERM (resumable).
"""

from __future__ import annotations

import sys
import types
from collections.abc import Sequence
from typing import Any

import coherent_jax
from coherent_jax.compat import warn_once
from coherent_jax.config import help_text, parse_overrides
from coherent_jax.run import launch, multihost
from coherent_jax.run.launch import describe_train, launch_train
from coherent_jax.run.loop_state import StopRequest


def train_help(items: Sequence[str] = ()) -> str:
    """``--help``: every option with the value `items` (the other arguments) resolve it to."""
    return help_text(parse_overrides(list(items)) if items else None, items)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m coherent_jax.train``: help, dry run or a run; its exit status. Bad input is one
    line on stderr and status 2, a divergence status 3 (`launch.refuse`)."""
    try:
        mode, items = launch.split_mode(list(sys.argv[1:] if argv is None else argv))
        if mode == launch.HELP:
            return launch.print_answer(train_help(items))
        if mode == launch.DRY:
            return launch.print_answer(describe_train(items))
        with StopRequest() as stop:  # SIGINT/SIGTERM: stop after the current iteration
            return launch_train(items, stop).status
    except launch.REFUSED as exc:
        return launch.refuse(exc)
    except KeyboardInterrupt:  # before the stop request took over
        return launch.interrupted()


class _CallableModule(types.ModuleType):
    """This module, callable as the function it was: ``coherent_jax.train(config)`` trained before
    `coherent_jax.learn` had that name, and still does, warning once (removed in 0.3).

    Why the module and not the package's ``__getattr__``: the package consults its
    ``__getattr__`` only while ``coherent_jax.train`` is not an attribute, and importing this
    module (``python -m coherent_jax.train``, ``from coherent_jax.train import main``) makes it
    one, so the call has to reach the module object itself. Only the object's class changes:
    the command line runs this file as before, word for word."""

    def __call__(self, config: Any = None, callbacks: Any = None) -> Any:
        warn_once("coherent_jax.train(config)", "coherent_jax.learn(config)")
        return coherent_jax.learn(config, callbacks)  # the package's lazy attribute: JAX from here on


sys.modules[__name__].__class__ = _CallableModule

if __name__ == "__main__":
    sys.exit(multihost.run_cli(main))

"""`Trainer`: what the host loop, sweeps and benchmarks use of a training algorithm.

Every trainer (`OnPolicyTrainer` for A2C/PPO, `SACTrainer`) has these pure,
jit-able functions of an explicit train state, whatever the algorithm; the loop
(`coherent_jax.run.loop`) jits, vmaps (a sweep's points) and shards them, and never
looks inside the state except through `export_params`.

It stands alone, small, because it is the one contract both algorithms' modules
implement and the loop, sweeps and benchmarks read, without importing either.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import jax

    from coherent_jax.envs.vec_env import VecEnv


class Trainer(Protocol):
    """A training algorithm as the loop drives it.

    Attributes:
      env: the vectorized training envs (the loop reports the physics engine that
        ``physics=auto`` resolved to, ``env.physics``).
      eval_env: the envs of the deterministic evaluation episodes.
    """

    env: VecEnv
    eval_env: VecEnv

    def init_hparams(self) -> Any:
        """The sweepable hyperparameters of the config, as the arrays the state holds."""

    def init(self, key: jax.Array, hparams: Any = None) -> Any:
        """The initial train state (``hparams``: a sweep point's; default `init_hparams`)."""

    def iteration(self, state: Any) -> tuple[Any, dict[str, jax.Array]]:
        """One training iteration: collect ``num_envs x unroll_length`` env steps, update."""

    def evaluate(self, state: Any, key: jax.Array) -> dict[str, jax.Array]:
        """Deterministic evaluation episodes: ``eval/*`` metrics."""

    def export_params(self, state: Any) -> dict[str, Any]:
        """What a policy needs on its own: policy parameters and observation statistics."""

"""Training algorithms. Every trainer exposes the same pure, jit-able functions (`Trainer`).

``init(key, hparams=None) -> state``, ``iteration(state) -> (state, metrics)``,
``evaluate(state, key) -> metrics`` and ``export_params(state) -> pytree`` (what
an evaluation needs: policy parameters and observation statistics). The train
loop, sweeps and benchmarks only use these, whatever the algorithm.
"""

from __future__ import annotations

from coherent_jax.agents.trainer import Trainer


def make_trainer(cfg, env=None, eval_env=None) -> Trainer:
    """The trainer of ``cfg.algo`` (A2C/PPO: `OnPolicyTrainer`; SAC: `SACTrainer`)."""
    if cfg.algo in ("ppo", "a2c"):
        from coherent_jax.agents.onpolicy import OnPolicyTrainer  # lazy: agents.trainer loads without JAX

        return OnPolicyTrainer(cfg, env, eval_env)
    if cfg.algo == "sac":
        from coherent_jax.agents.sac import SACTrainer  # lazy: as OnPolicyTrainer

        return SACTrainer(cfg, env, eval_env)
    raise ValueError(f"unknown algo {cfg.algo!r}")

"""A trained policy to ship: `load_policy(path)` -> `TrainedPolicy` with ``predict`` (Stable-Baselines3's
convention), actions in the env's own action space, stochastic acting with the strategy's noise
state, and the export formats of ``python -m coherent_jax.export`` (`coherent_jax.policy.onnx`,
`coherent_jax.policy.hub`)."""

from coherent_jax.policy.agent import PolicyState, TrainedPolicy, load_policy

__all__ = ["PolicyState", "TrainedPolicy", "load_policy"]

"""A trained policy to ship: `load_policy(path)` -> `Policy` with ``predict`` (Stable-Baselines3's
convention), actions in the env's own action space, stochastic acting with the strategy's noise
state, and the export formats of ``python -m coherent_jax.export`` (`coherent_jax.policy.formats`,
`coherent_jax.policy.hub`). `TrainedPolicy` is `Policy`'s former name."""

from coherent_jax.policy.net import PolicyError
from coherent_jax.policy.trained import Policy, PolicyState, TrainedPolicy, load_policy

__all__ = ["Policy", "PolicyError", "PolicyState", "TrainedPolicy", "load_policy"]

"""A trained policy to ship: `load_policy(path)` -> `Policy` with ``predict`` (Stable-Baselines3's
convention), actions in the env's own action space, stochastic acting with the strategy's noise
state, and the export formats of ``python -m coherent_jax.export`` (`coherent_jax.policy.formats`,
`coherent_jax.policy.hub`). `TrainedPolicy`, `Policy`'s former name, still answers (deprecated)."""

from coherent_jax.compat import module_getattr
from coherent_jax.policy.net import PolicyError
from coherent_jax.policy.trained import Policy, PolicyState, load_policy

__all__ = ["Policy", "PolicyError", "PolicyState", "load_policy"]
__getattr__ = module_getattr(__name__, {"TrainedPolicy": "coherent_jax.policy.Policy"})

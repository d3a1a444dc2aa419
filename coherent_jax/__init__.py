"""coherent_jax: Deep Coherent Exploration for continuous control, in JAX on MJX."""

__version__ = "0.1.0"

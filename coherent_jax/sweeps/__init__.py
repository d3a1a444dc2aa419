"""The parts of ``python -m coherent_jax.sweep`` beside its command: resuming a sweep
(`resume`) and its table of final returns (`table`)."""

"""Deep Coherent Exploration: the beta-chain over the policy's last layer and its inference.

`strategy` holds the strategies (`CoherentExploration` for A2C/PPO with its gradient
modes, `CoherentBehaviour` for SAC); `layer` what the on-policy ones share (the chain's
settings and the perturbed last layer); `filter` the exact recursive inference (thesis
eqs. 4.33-4.49); `joint` the same marginals from a segment's joint Gaussian; `exact` blocks
of the joint form chained by differentiable beliefs; `mc` the Monte Carlo and all-layers
ablations; `reference` the thesis's dense filter, a reference that training never runs (the
benchmarks and the tests check the block filter against it). The chain itself (eqs.
4.1-4.5) is `coherent_jax.exploration.chain`.
"""

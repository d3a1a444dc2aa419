"""Exploration strategies: one module per strategy, one interface (`base.Exploration`)."""

from __future__ import annotations

from coherent_jax.exploration.base import ActOutput, Exploration, SegmentLogProb


def make_exploration(cfg, action_size: int) -> Exploration:
    """The strategy named by ``cfg.explore``, built for ``action_size`` actions."""
    if cfg.explore == "action":
        from coherent_jax.exploration.action import ActionNoise

        return ActionNoise(action_size, cfg.policy_hidden, cfg.activation, cfg.init_std)
    if cfg.explore == "coherent" and cfg.coherent.layers == "all":
        from coherent_jax.exploration.coherent_mc import CoherentAllLayers

        return CoherentAllLayers(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            beta=cfg.beta,
            w_std_init=cfg.w_std_init,
            action_std=cfg.action_std,
            learn_action_std=cfg.learn_action_std,
        )
    if cfg.explore == "coherent":
        from coherent_jax.exploration.coherent import CoherentExploration
        from coherent_jax.exploration.coherent_mc import CoherentMC

        cls = CoherentMC if cfg.coherent.integration == "mc" else CoherentExploration
        return cls(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            beta=cfg.beta,
            w_std_init=cfg.w_std_init,
            action_std=cfg.action_std,
            learn_action_std=cfg.learn_action_std,
            remat=cfg.remat,
            inference=cfg.coherent_inference,
            gradient=cfg.coherent.gradient,
            sigma_init=cfg.sigma_init,
            sigma_delta=cfg.sigma_delta,
            sigma_alpha=cfg.sigma_alpha,
        )
    if cfg.explore == "noisynet":
        from coherent_jax.exploration.noisynet import NoisyNet

        return NoisyNet(action_size, cfg.policy_hidden, cfg.activation, cfg.init_std, cfg.noisynet_sigma0)
    if cfg.explore == "psne":
        from coherent_jax.exploration.psne import ParameterNoise

        return ParameterNoise(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            cfg.init_std,
            sigma_init=cfg.sigma_init,
            sigma_delta=cfg.sigma_delta,
            sigma_alpha=cfg.sigma_alpha,
        )
    if cfg.explore == "gsde":
        from coherent_jax.exploration.gsde import GeneralizedSDE

        return GeneralizedSDE(
            action_size, cfg.policy_hidden, cfg.activation, cfg.init_std, cfg.gsde_resample_every
        )
    if cfg.explore == "pink":
        from coherent_jax.exploration.pink import PinkNoise

        return PinkNoise(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            cfg.init_std,
            cfg.pink_exponent,
            cfg.episode_length,
        )
    raise ValueError(f"unknown explore {cfg.explore!r}")


__all__ = ["ActOutput", "Exploration", "SegmentLogProb", "make_exploration"]

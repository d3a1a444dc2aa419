"""Exploration strategies: one module per strategy, one interface (`base.Exploration`)."""

from __future__ import annotations

from coherent_jax.exploration.base import ActOutput, Exploration, SegmentLogProb


def make_exploration(cfg, action_size: int) -> Exploration:
    """The strategy named by ``cfg.explore``, built for ``action_size`` actions."""
    if cfg.explore == "action":
        from coherent_jax.exploration.action import ActionNoise

        return ActionNoise(action_size, cfg.policy_hidden, cfg.activation, cfg.init_std)
    if cfg.explore == "coherent":
        from coherent_jax.exploration.coherent import CoherentExploration

        return CoherentExploration(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            beta=cfg.beta,
            w_std_init=cfg.w_std_init,
            action_std=cfg.action_std,
            learn_action_std=cfg.learn_action_std,
            remat=cfg.remat,
            inference=cfg.coherent_inference,
            sigma_init=cfg.sigma_init,
            sigma_delta=cfg.sigma_delta,
            sigma_alpha=cfg.sigma_alpha,
        )
    raise ValueError(f"unknown explore {cfg.explore!r}")


__all__ = ["ActOutput", "Exploration", "SegmentLogProb", "make_exploration"]

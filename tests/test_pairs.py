"""Every valid (algo, explore) pair trains on pointmass; every other pair is refused.

One short run per pair from the real config with small overrides: the losses stay
finite and the mean train return of the last quarter of the run is clearly above
the first quarter's. The same compiled iteration, re-run from the same seed,
reproduces the first iterations exactly. A frozen policy (lr = 0, same program)
shows that the margin is not met without learning.
"""

import jax
import numpy as np
import pytest

from coherent_jax.agents import make_trainer
from coherent_jax.config import ALGOS, EXPLORES, SUPPORTED_ALGOS, ConfigError, parse_overrides

# pointmass, 50-step episodes, 16 envs x 32 steps per iteration, PPO's default 10
# epochs x 4 minibatches. Returns start near -45..-60 (an untrained policy) and rise
# towards -20. A2C takes one gradient step per iteration, hence its larger lr.
BASE = [
    "env=pointmass",
    "episode_length=50",
    "num_envs=16",
    "unroll_length=32",
    "ppo.num_minibatches=4",
    "eval_episodes=2",
    "progress=false",
]
ALGO_EXTRA = {"ppo": [], "a2c": ["lr=3e-3"]}
ITERATIONS = 100
MARGIN = 5.0
# Single-sample gradients credit only the action noise (thesis eq. 4.8): at the
# defaults (action_std = w_std_init = 0.1) these ablations did not learn within
# this budget, and layers=last not even at w_std_init = 0.03 (seed 0: -52 -> -53);
# with the weight noise well below the action noise they do (seeds 0 and 1).
MC_ALL = ["coherent.beta=0.1", "coherent.action_std=0.3", "coherent.w_std_init=0.03"]
MC = ["coherent.beta=0.1", "coherent.action_std=0.3", "coherent.w_std_init=0.01"]
# (algo, explore overrides, extra settings for this pair)
PAIRS = [
    ("ppo", ["explore=action"], []),
    ("a2c", ["explore=action"], []),
    ("ppo", ["explore=coherent"], ["coherent.beta=0.1"]),
    ("a2c", ["explore=coherent"], ["coherent.beta=0.1"]),
    ("ppo", ["explore=coherent", "coherent.integration=mc"], MC),
    ("a2c", ["explore=coherent", "coherent.integration=mc"], MC),
    ("ppo", ["explore=coherent", "coherent.integration=mc", "coherent.layers=all"], MC_ALL),
    ("a2c", ["explore=coherent", "coherent.integration=mc", "coherent.layers=all"], MC_ALL),
    ("ppo", ["explore=noisynet"], []),
    ("a2c", ["explore=noisynet"], []),
    ("ppo", ["explore=psne"], []),
    ("a2c", ["explore=psne"], []),
    ("ppo", ["explore=gsde"], []),
    ("a2c", ["explore=gsde"], []),
    ("ppo", ["explore=pink"], []),
    ("a2c", ["explore=pink"], []),
    ("ppo", ["explore=lattice"], []),
    ("a2c", ["explore=lattice"], []),
]


def pair_id(pair):
    algo, explore, _ = pair
    return algo + "-" + "-".join(e.split("=")[1] for e in explore)


def run(cfg):
    """A function (iterations, lr_scale) -> per-iteration metrics, compiled once for ``cfg``."""
    trainer = make_trainer(cfg)
    init = jax.jit(trainer.init)
    iteration = jax.jit(trainer.iteration)

    def go(n, lr_scale=1.0, seed=None):
        key = jax.random.PRNGKey(cfg.seed if seed is None else seed)
        hp = trainer.init_hparams()
        if lr_scale != 1.0:
            hp = hp.replace(lr=hp.lr * lr_scale)
        state = init(key, hp)
        rows = []
        for _ in range(n):
            state, metrics = iteration(state)
            rows.append({k: float(v) for k, v in jax.device_get(metrics).items()})
        go.final_state = state
        return rows

    go.evaluate = jax.jit(trainer.evaluate)
    return go


def quarter_means(rows):
    returns = np.array([r["train/episode_return"] for r in rows])
    k = len(returns) // 4
    return float(np.nanmean(returns[:k])), float(np.nanmean(returns[-k:]))


@pytest.mark.slow
@pytest.mark.parametrize("pair", PAIRS, ids=[pair_id(p) for p in PAIRS])
def test_pair_trains_on_pointmass(pair):
    algo, explore, extra = pair
    cfg = parse_overrides([*BASE, f"algo={algo}", *explore, *extra, *ALGO_EXTRA[algo]])
    go = run(cfg)
    rows = go(ITERATIONS)
    for key in ("train/policy_loss", "train/value_loss", "train/entropy", "train/grad_norm"):
        assert all(np.isfinite(r[key]) for r in rows), key
    early, late = quarter_means(rows)
    print(f"{pair_id(pair)}: train return first quarter {early:.1f}, last quarter {late:.1f}")
    assert late > early + MARGIN, (early, late)
    # Same seed, same program: the first iterations repeat exactly.
    np.testing.assert_equal(go(2), rows[:2])


# SAC on pointmass as in tests/test_sac.py (100-step episodes, 10,240 steps, about -100
# for an untrained policy); action and coherent (Coherent-SAC) are tested there.
SAC_BASE = [
    "env=pointmass",
    "algo=sac",
    "num_envs=8",
    "unroll_length=16",
    "episode_length=100",
    "policy_hidden=[64,64]",
    "value_hidden=[64,64]",
    "sac.warmup_steps=1024",
    "sac.utd_ratio=0.5",
    "eval_episodes=16",
    "progress=false",
]
SAC_ITERATIONS = 80
SAC_PAIRS = [["explore=psne"], ["explore=gsde"], ["explore=pink"], ["explore=lattice"]]


@pytest.mark.slow
@pytest.mark.parametrize("explore", SAC_PAIRS, ids=lambda e: "sac-" + e[0].split("=")[1])
def test_sac_pair_trains_on_pointmass(explore):
    cfg = parse_overrides([*SAC_BASE, *explore])
    go = run(cfg)
    rows = go(SAC_ITERATIONS)
    updated = [r for r in rows if r["train/updates_applied"] > 0]
    assert len(updated) > SAC_ITERATIONS // 2
    for key in ("train/critic_loss", "train/actor_loss"):
        assert all(np.isfinite(r[key]) for r in updated), key
    early, late = quarter_means(rows)
    final = float(go.evaluate(go.final_state, jax.random.PRNGKey(1))["eval/episode_return"])
    print(
        f"sac-{explore[0]}: train return first quarter {early:.1f}, last quarter {late:.1f}, eval {final:.1f}"
    )
    assert late > early + MARGIN, (early, late)
    assert final >= -40.0
    if explore == ["explore=psne"]:
        assert len({r["train/sigma"] for r in updated}) > 1  # sigma adapts (4.51)
    np.testing.assert_equal(go(2), rows[:2])


@pytest.mark.slow
def test_frozen_policy_does_not_meet_the_margin():
    """Control for the assertion above: lr = 0 in the same program, the return does not rise."""
    cfg = parse_overrides([*BASE, "algo=ppo", "explore=action"])
    rows = run(cfg)(ITERATIONS, lr_scale=0.0)
    early, late = quarter_means(rows)
    assert not late > early + MARGIN, (early, late)


def test_every_pair_is_listed_or_refused_with_a_reason():
    """The table above covers every on-policy pair that SUPPORTED_ALGOS allows; the others
    are refused at start-up in one line that names the pair and why."""
    covered = {(a, e[0].split("=")[1]) for a, e, _ in PAIRS}
    covered |= {("sac", e[0].split("=")[1]) for e in SAC_PAIRS}
    for explore in EXPLORES:
        for algo in ALGOS:
            overrides = [f"algo={algo}", f"explore={explore}"]
            if algo in SUPPORTED_ALGOS[explore]:
                parse_overrides(overrides)
                assert (algo, explore) in covered or algo == "sac" and explore in ("action", "coherent")
            else:
                with pytest.raises(ConfigError) as err:
                    parse_overrides(overrides)
                msg = str(err.value)
                assert "\n" not in msg and f"explore={explore}" in msg and ": " in msg.split("(allowed:")[1]

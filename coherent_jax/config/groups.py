"""How a config field is declared, and the groups: an algorithm's or a strategy's own settings.

A field declares everything about itself in its metadata: the one-line help
(``--help``), the allowed values (``choices``) or range (``check``: a predicate and the
text of what it allows), the help section of a top-level field (``group``), for a
sweepable scalar a `Sweepable`, and the text of the allowed values where they are no
fixed list (``allowed``: the env's). `coherent_jax.config.checks` validates from these
declarations.

A group is the settings of one algorithm or one strategy, a dataclass of such fields that
is one field of the config (``ppo.*``, ``sac.*``, ``coherent.*``, ...; `coherent_jax.config.schema`).
The keys a setting had before are `coherent_jax.config.parse`'s. No JAX here.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

from coherent_jax.strategies import ALGOS, EXPLORES, ON_POLICY


# ------------------------------------------------------------------ how a field is declared
@dataclasses.dataclass(frozen=True)
class Sweepable:
    """Marks a scalar that lives in the train state as an array, so a vmapped sweep may vary it.

    Attributes:
      reads: the (algos, explores) pairs whose train state holds it; a sweep axis
        for any other pair would run identical points and is refused.
      hparam: its typed path in the trainer's hyperparameters, field names joined by dots
        (e.g. ``explore.beta``: the strategy's own dataclass), when that is not the key's
        last part (a field of the trainer's own).
    """

    reads: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]
    hparam: str | None = None

    def read_by(self, algo: str, explore: str) -> bool:
        return any(algo in algos and explore in explores for algos, explores in self.reads)


# --- declared ranges: (predicate, what is allowed)
Check = tuple[Callable[[Any], bool], str]


def number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


POSITIVE: Check = (lambda v: number(v) and v > 0, "a finite number > 0")
NON_NEGATIVE: Check = (lambda v: number(v) and v >= 0, "a finite number >= 0")
UNIT: Check = (lambda v: number(v) and 0.0 <= v <= 1.0, "a number in [0, 1]")


def at_least(low: int, allowed: str | None = None, below: int | None = None) -> Check:
    """An integer >= ``low`` (and < ``below``, if given)."""
    return (
        lambda v: v >= low and (below is None or v < below),
        allowed or f"an integer >= {low}",
    )


COUNT = at_least(1, below=2**31)  # sizes and counts held in int32 counters
LAYERS: Check = (lambda v: len(v) >= 1 and all(n >= 1 for n in v), "a list of ints >= 1")


def field(
    default: Any,
    help: str,
    *,
    group: str | None = None,
    check: Check | None = None,
    choices: tuple[Any, ...] | None = None,
    sweep: Sweepable | None = None,
    allowed: str | None = None,
) -> Any:
    """A config field with its help and declarations (see the module's docstring)."""
    metadata: dict[str, Any] = {"help": help}
    for name, value in (
        ("group", group),
        ("check", check),
        ("choices", choices),
        ("sweep", sweep),
        ("allowed", allowed),
    ):
        if value is not None:
            metadata[name] = value
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def sweep(*reads: tuple[tuple[str, ...], tuple[str, ...]], hparam: str | None = None) -> Sweepable:
    return Sweepable(reads=tuple(reads), hparam=hparam)


EVERY = (ALGOS, EXPLORES)
ON_POLICY_ALL = (ON_POLICY, EXPLORES)
SAC_ALL = (("sac",), EXPLORES)
# The adaptive-sigma rule (4.50)-(4.51): PSNE's with every algorithm (sigma itself is in the
# state with SAC only: on-policy it is per-env state), Coherent-SAC's for its chain's scale.
PSNE_SAC = (("sac",), ("psne",))
SIGMA_RULE = (PSNE_SAC, (ON_POLICY, ("psne",)))
COHERENT_SAC = (("sac",), ("coherent",))


class Group:
    """A group's ``__str__``: ``{key=value,...}``, as a log line shows it."""

    def __str__(self) -> str:
        return "{" + ",".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self)) + "}"


# ------------------------------------------------------------------ the groups
COHERENT_INTEGRATION = ("analytic", "mc")
COHERENT_LAYERS = ("last", "all")
COHERENT_GRADIENT = ("exact", "stored", "episode")
COHERENT_INFERENCE = ("joint", "filter")


@dataclasses.dataclass
class PPOOptions(Group):
    """A2C's and PPO's settings (``ppo.<key>=value``; A2C takes one gradient step per iteration)."""

    gae_lambda: float = field(0.95, "GAE lambda (eq. 2.30)", check=UNIT, sweep=sweep(ON_POLICY_ALL))
    num_epochs: int = field(10, "PPO epochs per iteration (A2C: 1 gradient step)", check=COUNT)
    num_minibatches: int = field(8, "minibatches per epoch; they split envs, never time", check=at_least(1))
    clip_eps: float = field(
        0.2, "PPO clipping epsilon (eq. 2.41)", check=POSITIVE, sweep=sweep(ON_POLICY_ALL)
    )
    target_kl: float = field(
        0.0,
        "stop the epochs once approx KL > 1.5 * target_kl; 0 = never",
        check=NON_NEGATIVE,
        sweep=sweep(ON_POLICY_ALL),
    )
    vf_coef: float = field(0.5, "weight of the value loss", check=NON_NEGATIVE, sweep=sweep(ON_POLICY_ALL))
    vf_lr: float = field(
        0.0,
        "the value's own Adam rate (with vf_iters); 0 = joint loss",
        check=NON_NEGATIVE,
        sweep=sweep(ON_POLICY_ALL),
    )
    vf_iters: int = field(0, "full-batch value steps per iteration after the policy's; 0 = joint loss")
    ent_coef: float = field(
        0.0, "weight of the entropy bonus", check=NON_NEGATIVE, sweep=sweep(ON_POLICY_ALL)
    )
    max_grad_norm: float = field(0.5, "global gradient-norm clip; 0 = none", check=NON_NEGATIVE)
    normalize_advantages: bool = field(True, "standardise advantages per minibatch")
    normalize_rewards: bool = field(
        False,
        "divide rewards by the running std of each env's discounted return, clipped "
        "to [-10, 10] (SB3's VecNormalize, CleanRL's NormalizeReward)",
    )


@dataclasses.dataclass
class SACOptions(Group):
    """SAC's settings (thesis Algorithm 3 and §4.3), ``sac.<key>=value``."""

    buffer_size: int = field(
        1_000_000,
        "replay capacity in transitions (a ring buffer in the state)",
        check=at_least(1),
    )
    batch_size: int = field(256, "transitions per gradient update", check=at_least(1))
    utd_ratio: float = field(
        1.0,
        "gradient updates per env step (per iteration: utd_ratio * num_envs * unroll_length)",
        check=POSITIVE,
    )
    warmup_steps: int = field(5000, "env steps of uniform random actions", check=at_least(0))
    update_after: int | None = field(
        None,
        "env steps before updates start; null = warmup_steps",
        check=(lambda v: v is None or 0 <= v < 2**31, "an integer >= 0 or null"),
    )
    tau: float = field(
        0.005,
        "Polyak step, target <- (1 - tau) target + tau online (rho = 1 - tau)",
        check=(lambda v: number(v) and 0 < v <= 1, "a number in (0, 1]"),
        sweep=sweep(SAC_ALL),
    )
    temperature: float = field(
        0.2,
        "entropy temperature alpha (initial value if auto_temperature)",
        check=POSITIVE,
        sweep=sweep(SAC_ALL),
    )
    auto_temperature: bool = field(False, "adapt alpha towards target_entropy (thesis: fixed)")
    target_entropy: float | None = field(
        None,
        "auto_temperature's entropy target; null = -action_size",
        check=(lambda v: v is None or number(v), "a finite number or null"),
    )


@dataclasses.dataclass
class CoherentOptions(Group):
    """The coherent strategy's settings and ablations (thesis §5), ``coherent.<key>=value``."""

    beta: float = field(
        0.01,
        "chain coefficient: 1 = fresh weights every step; 0 = one draw per chain, which restarts every "
        "unroll_length steps under coherent.gradient=exact (the default) and at episode starts only "
        "under gradient=episode or stored, integration=mc and algo=sac (docs/coherent.md)",
        check=UNIT,
        sweep=sweep((ALGOS, ("coherent",)), hparam="explore.beta"),
    )
    w_std_init: float = field(
        0.1,
        "initial std of the last-layer weights (Lambda^-1/2); 0.1 gives an initial action std of about 0.45",
        check=POSITIVE,
    )
    action_std: float = field(0.1, "std of the action given the weights (Lambda_a^-1/2)", check=POSITIVE)
    learn_action_std: bool = field(False, "learn action_std (thesis: fixed)")
    inference: str = field(
        "joint",
        "how w is integrated out: joint (Cholesky of each segment's joint Gaussian, fast up to a "
        "few hundred steps per segment) or filter (sequential scan)",
        choices=COHERENT_INFERENCE,
    )
    remat: bool = field(
        False,
        "rematerialise the filter scan or the chained blocks in the backward pass (less memory, more time)",
    )
    integration: str = field(
        "analytic",
        "analytic (integrate w out: the filter, A2C/PPO only) or mc "
        "(single-sample Monte Carlo: log-prob of the sampled w_t)",
        choices=COHERENT_INTEGRATION,
    )
    layers: str = field(
        "last",
        "last (the beta-chain on the last layer) or all (on every layer's weights; needs integration=mc, "
        "on-policy)",
        choices=COHERENT_LAYERS,
    )
    gradient: str = field(
        "exact",
        "analytic: exact (the chain restarts at each segment start, as at t = 0 of Algorithm 5: the "
        "thesis's gradient of a chain cut every unroll_length steps), episode (the chain runs on through "
        "the episode; the loss re-infers each segment's episode prefix under the current parameters: the "
        "thesis's gradient of that chain) or stored (the chain runs on; a segment starts from the belief "
        "stored at collection, held constant)",
        choices=COHERENT_GRADIENT,
    )
    episode_restart: bool = field(
        True,
        "restart the chain at every episode start (false: the chain runs across resets within a segment, "
        "as the thesis's buffer does)",
    )


@dataclasses.dataclass
class NoisyNetOptions(Group):
    """NoisyNet's setting, ``noisynet.<key>=value``."""

    sigma0: float = field(
        0.5,
        "initial noise scale sigma_0; each layer's sigma starts at sigma_0 / sqrt(fan_in)",
        check=POSITIVE,
    )


SIGMA_ALPHA = (lambda v: number(v) and v > 1, "a number > 1")


@dataclasses.dataclass
class CoherentSACOptions(Group):
    """Coherent-SAC's chain scale (thesis §4.3): W_t = W + sigma z_t, sigma adapted by
    (4.50)-(4.51) as PSNE's, ``coherent_sac.<key>=value`` (``psne.*`` before, still read with a note)."""

    sigma_init: float = field(
        0.1,
        "initial scale sigma of the chain around the actor's mean head, W_t = W + sigma z_t "
        "(w_std = sigma; 0 gives plain SAC's actions)",
        check=NON_NEGATIVE,
        sweep=sweep(COHERENT_SAC, hparam="explore.sigma"),
    )
    sigma_delta: float = field(
        0.1,
        "distance threshold delta of the sigma rule (4.51)",
        check=POSITIVE,
        sweep=sweep(COHERENT_SAC, hparam="explore.sigma_delta"),
    )
    sigma_alpha: float = field(
        1.01,
        "scaling factor alpha > 1 of the sigma rule (4.51)",
        check=SIGMA_ALPHA,
        sweep=sweep(COHERENT_SAC, hparam="explore.sigma_alpha"),
    )


@dataclasses.dataclass
class PsneOptions(Group):
    """Parameter-space noise's adaptive sigma (4.50)-(4.51), ``psne.<key>=value``."""

    sigma_init: float = field(
        0.1,
        "initial parameter-noise scale sigma",
        check=NON_NEGATIVE,
        sweep=sweep(SIGMA_RULE[0], hparam="explore.sigma"),
    )
    sigma_delta: float = field(
        0.1,
        "distance threshold delta of the sigma rule (4.51)",
        check=POSITIVE,
        sweep=sweep(*SIGMA_RULE, hparam="explore.sigma_delta"),
    )
    sigma_alpha: float = field(
        1.01,
        "scaling factor alpha > 1 of the sigma rule (4.51)",
        check=SIGMA_ALPHA,
        sweep=sweep(*SIGMA_RULE, hparam="explore.sigma_alpha"),
    )


@dataclasses.dataclass
class GsdeOptions(Group):
    """gSDE's setting, ``gsde.<key>=value``."""

    resample_every: int = field(
        4,
        "steps between redraws of the noise matrix (also redrawn at each episode start)",
        check=COUNT,
    )


@dataclasses.dataclass
class PinkOptions(Group):
    """Coloured noise's setting, ``pink.<key>=value``."""

    exponent: float = field(
        1.0,
        "noise spectrum ~ 1/f^exponent (0 white, 1 pink, 2 red)",
        check=(lambda v: number(v) and 0 <= v <= 4, "a number in [0, 4] (0 white, 1 pink, 2 red)"),
    )


@dataclasses.dataclass
class LatticeOptions(Group):
    """Lattice's settings, ``lattice.<key>=value`` (`coherent_jax.exploration.lattice`)."""

    resample_every: int = field(
        4,
        "steps between redraws of the noise matrices P_x and P_a (also redrawn at each episode start)",
        check=COUNT,
    )
    init_std: float = field(
        0.5,
        "initial std s of the noise matrices' entries, each s / sqrt(d) for d latent features "
        "(learned; clipped to [0.001, 10])",
        check=(lambda v: number(v) and 1e-3 <= v <= 10.0, "a number in [0.001, 10] (the stds' clip range)"),
    )
    alpha: float = field(
        1.0,
        "weight of the latent noise P_x beside the action noise P_a (0: gSDE's noise alone)",
        check=NON_NEGATIVE,
    )
    action_noise: bool = field(
        True, "independent action noise P_a x beside the latent noise (false: latent noise alone)"
    )
    weight_grad: bool = field(
        True,
        "the covariance's last-layer weights W carry the loss's gradient (true, as the reference code); "
        "false detaches them, so the covariance trains the stds alone",
    )
    std_reg: float = field(
        0.0,
        "std of white noise added to every action dimension (on-policy; a floor on the covariance)",
        check=NON_NEGATIVE,
    )
    head_gain: float = field(
        0.01,
        "orthogonal init gain of the policy's (SAC: the actor's) mean head W, every strategy's 0.01: Lattice "
        "starts as gSDE and its latent noise grows with W; 0.57735 (1/sqrt(3), the reference's PyTorch "
        "default) makes it a quarter of the action variance from the start",
        check=POSITIVE,
    )

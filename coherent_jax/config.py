"""Typed, validated run configuration with ``key=value`` overrides.

The configuration is one dataclass; OmegaConf turns it into a structured config,
so ``key=value`` overrides on the command line (Hydra's syntax) are type-checked
on merge. Ranges and choices are checked here, and every problem becomes a
`ConfigError` whose one-line message names the key and what is allowed.

Every field carries its metadata: its group (`GROUPS`, the sections of ``--help``),
a one-line help and, for a sweepable scalar, a `Sweepable` saying which
(algo, explore) pairs hold it in the train state. Shape-determining settings
(``num_envs``, ``unroll_length``, network sizes, ...) are static Python values; the
sweepable scalars (`SWEEPABLE`, derived from the fields) become arrays inside the
train state so that `jax.vmap` can run a grid of them as one program.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from coherent_jax import limits
from coherent_jax.envs.registry import (
    DEFAULT_THREADS,
    NATIVE_TASKS,
    PHYSICS,
    TASKS,
    PhysicsError,
    resolve_physics,
)
from coherent_jax.presets import NO_PRESET, PRESETS, help_lines, layered_base
from coherent_jax.strategies import ALGOS, EXPLORES, ON_POLICY, REFUSED, SUPPORTED_ALGOS

COHERENT_INTEGRATION = ("analytic", "mc")
COHERENT_LAYERS = ("last", "all")
COHERENT_GRADIENT = ("exact", "stored", "episode")
ACTIVATIONS = ("tanh", "relu", "elu", "swish")
COHERENT_INFERENCE = ("joint", "filter")


@dataclasses.dataclass
class CoherentOptions:
    """The coherent strategy's ablations (thesis §5), set as ``coherent.<key>=value``."""

    integration: str = dataclasses.field(
        default="analytic",
        metadata={
            "help": "coherent: analytic (integrate w out: the filter, A2C/PPO only) or mc "
            "(single-sample Monte Carlo: log-prob of the sampled w_t)"
        },
    )
    layers: str = dataclasses.field(
        default="last",
        metadata={
            "help": "coherent: last (the beta-chain on the last layer) or all (on every layer's "
            "weights; needs integration=mc, on-policy)"
        },
    )
    gradient: str = dataclasses.field(
        default="exact",
        metadata={
            "help": "coherent, analytic: exact (the chain restarts at each segment start, as at t = 0 "
            "of Algorithm 5: the thesis's gradient of a chain cut every unroll_length steps), episode "
            "(the chain runs on through the episode; the loss re-infers each segment's episode prefix "
            "under the current parameters: the thesis's gradient of that chain) or stored (the chain "
            "runs on; a segment starts from the belief stored at collection, held constant)"
        },
    )
    episode_restart: bool = dataclasses.field(
        default=True,
        metadata={
            "help": "coherent: restart the chain at every episode start (false: the chain runs across "
            "resets within a segment, as the thesis's buffer does)"
        },
    )

    def __str__(self) -> str:
        return "{" + ",".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self)) + "}"


# Option groups, in the order `help_text` prints them; every field names its group.
GROUPS = (
    "run",
    "collection",
    "optimisation",
    "networks",
    "exploration",
    "sac",
    "output",
    "physics",
    "devices",
)


@dataclasses.dataclass(frozen=True)
class Sweepable:
    """Marks a scalar that lives in the train state as an array, so a vmapped sweep may vary it.

    Attributes:
      reads: the (algos, explores) pairs whose train state holds it; a sweep axis
        for any other pair would run identical points and is refused.
      hparam: its name in the state's hyperparameters when that is not the key's own.
    """

    reads: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]
    hparam: str | None = None

    def read_by(self, algo: str, explore: str) -> bool:
        return any(algo in algos and explore in explores for algos, explores in self.reads)


def _field(group: str, default: Any, help: str, sweep: Sweepable | None = None, **kw: Any) -> Any:
    """A config field with its group, its one-line help and, if sweepable, who reads it."""
    metadata = {"group": group, "help": help}
    if sweep is not None:
        metadata["sweep"] = sweep
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=metadata, **kw)
    return dataclasses.field(default=default, metadata=metadata, **kw)


def _sweep(*reads: tuple[tuple[str, ...], tuple[str, ...]], hparam: str | None = None) -> Sweepable:
    return Sweepable(reads=tuple(reads), hparam=hparam)


_EVERY = (ALGOS, EXPLORES)
_ON_POLICY = (ON_POLICY, EXPLORES)
_SAC = (("sac",), EXPLORES)
# The adaptive-sigma rule (4.50)-(4.51): PSNE everywhere, Coherent-SAC (its chain's scale).
_SIGMA_RULE = ((("sac",), ("coherent", "psne")), (ON_POLICY, ("psne",)))


@dataclasses.dataclass
class Config:
    """Everything that defines a training run (see ``--help``)."""

    # --- what to run
    env: str = _field("run", "halfcheetah", "task name: " + ", ".join(TASKS))
    algo: str = _field(
        "run", "ppo", "algorithm: " + ", ".join(ALGOS) + " (sac changes some defaults: see ALGO_DEFAULTS)"
    )
    explore: str = _field("run", "action", "exploration strategy: " + ", ".join(EXPLORES))
    preset: str | None = _field(
        "run", "", "a protocol's values over the algo's defaults: " + ", ".join(PRESETS)
    )
    seed: int = _field("run", 0, "PRNG seed; the same seed gives the same run")
    total_steps: int = _field("run", 2_000_000, "environment steps to train for")
    # --- collection
    num_envs: int = _field("collection", 64, "parallel environments")
    unroll_length: int = _field("collection", 64, "steps per env per iteration (segment length T)")
    episode_length: int = _field(
        "collection",
        0,
        "time limit in env steps (truncation is bootstrapped); 0 = the task's own (1000; reacher 50)",
    )
    # --- optimisation
    lr: float = _field("optimisation", 3e-4, "Adam learning rate (policy and value)", _sweep(_EVERY))
    gamma: float = _field("optimisation", 0.99, "discount factor", _sweep(_EVERY))
    gae_lambda: float = _field("optimisation", 0.95, "GAE lambda (eq. 2.30)", _sweep(_ON_POLICY))
    num_epochs: int = _field("optimisation", 10, "PPO epochs per iteration (A2C: 1 gradient step)")
    num_minibatches: int = _field("optimisation", 8, "minibatches per epoch; they split envs, never time")
    clip_eps: float = _field("optimisation", 0.2, "PPO clipping epsilon (eq. 2.41)", _sweep(_ON_POLICY))
    target_kl: float = _field(
        "optimisation",
        0.0,
        "stop the epochs once approx KL > 1.5 * target_kl; 0 = never",
        _sweep(_ON_POLICY),
    )
    vf_coef: float = _field("optimisation", 0.5, "weight of the value loss", _sweep(_ON_POLICY))
    vf_lr: float = _field(
        "optimisation",
        0.0,
        "a2c/ppo: the value's own Adam rate (with vf_iters); 0 = joint loss",
        _sweep(_ON_POLICY),
    )
    vf_iters: int = _field(
        "optimisation", 0, "a2c/ppo: full-batch value steps per iteration after the policy's; 0 = joint loss"
    )
    ent_coef: float = _field("optimisation", 0.0, "weight of the entropy bonus", _sweep(_ON_POLICY))
    max_grad_norm: float = _field("optimisation", 0.5, "global gradient-norm clip; 0 = none")
    normalize_advantages: bool = _field("optimisation", True, "standardise advantages per minibatch")
    normalize_obs: bool = _field("optimisation", True, "running mean/std observation normalisation")
    normalize_rewards: bool = _field(
        "optimisation",
        False,
        "a2c/ppo: divide rewards by the running std of each env's discounted return, clipped "
        "to [-10, 10] (SB3's VecNormalize, CleanRL's NormalizeReward)",
    )
    # --- networks
    policy_hidden: list[int] = _field("networks", [64, 64], "policy trunk layer sizes")
    value_hidden: list[int] = _field("networks", [64, 64], "value network layer sizes")
    activation: str = _field("networks", "tanh", "hidden activation: " + ", ".join(ACTIVATIONS))
    # --- exploration
    init_std: float = _field("exploration", 0.5, "action noise: initial std of the Gaussian policy")
    beta: float = _field(
        "exploration",
        0.01,
        "coherent: chain coefficient, 1 = step-based, 0 = trajectory-based",
        _sweep((ALGOS, ("coherent",))),
    )
    w_std_init: float = _field(
        "exploration",
        0.1,
        "coherent: initial std of the last-layer weights (Lambda^-1/2); "
        "0.1 gives an initial action std of about 0.45",
    )
    action_std: float = _field(
        "exploration", 0.1, "coherent: std of the action given the weights (Lambda_a^-1/2)"
    )
    learn_action_std: bool = _field("exploration", False, "coherent: learn action_std (thesis: fixed)")
    coherent_inference: str = _field(
        "exploration",
        "joint",
        "coherent: how w is integrated out: joint (Cholesky of each segment's joint "
        "Gaussian, fast up to a few hundred steps per segment) or filter (sequential scan)",
    )
    remat: bool = _field(
        "exploration",
        False,
        "coherent: rematerialise the filter scan or the chained blocks in the backward pass "
        "(less memory, more time)",
    )
    # --- off-policy (SAC, thesis Algorithm 3 and §4.3)
    buffer_size: int = _field(
        "sac", 1_000_000, "sac: replay capacity in transitions (a ring buffer in the state)"
    )
    batch_size: int = _field("sac", 256, "sac: transitions per gradient update")
    utd_ratio: float = _field(
        "sac", 1.0, "sac: gradient updates per env step (per iteration: utd_ratio * num_envs * unroll_length)"
    )
    warmup_steps: int = _field("sac", 5000, "sac: env steps of uniform random actions")
    update_after: int | None = _field("sac", None, "sac: env steps before updates start; null = warmup_steps")
    tau: float = _field(
        "sac",
        0.005,
        "sac: Polyak step, target <- (1 - tau) target + tau online (rho = 1 - tau)",
        _sweep(_SAC),
    )
    temperature: float = _field(
        "sac", 0.2, "sac: entropy temperature alpha (initial value if auto_temperature)", _sweep(_SAC)
    )
    auto_temperature: bool = _field("sac", False, "sac: adapt alpha towards target_entropy (thesis: fixed)")
    target_entropy: float | None = _field(
        "sac", None, "sac: auto_temperature's entropy target; null = -action_size"
    )
    sigma_init: float = _field(
        "sac",
        0.1,
        "coherent-sac and psne: initial parameter-noise scale sigma (w_std = sigma)",
        _sweep(_SIGMA_RULE[0], hparam="sigma"),
    )
    sigma_delta: float = _field(
        "sac",
        0.1,
        "coherent-sac and psne: distance threshold delta of the sigma rule (4.51)",
        _sweep(*_SIGMA_RULE),
    )
    sigma_alpha: float = _field(
        "sac",
        1.01,
        "coherent-sac and psne: scaling factor alpha > 1 of the sigma rule (4.51)",
        _sweep(*_SIGMA_RULE),
    )
    # --- evaluation and output
    eval_every: int = _field(
        "output", 10, "iterations between deterministic evaluations; 0 = only at the end"
    )
    eval_episodes: int = _field("output", 8, "episodes per evaluation (run in parallel)")
    run_dir: str = _field(
        "output", "", "output directory; default runs/<env>-<algo>-<explore>-s<seed>-<time>"
    )
    progress: bool = _field("output", True, "show a progress bar")
    # --- long runs: checkpoints, resume, TensorBoard
    checkpoint_every: int = _field(
        "output",
        10,
        "iterations between checkpoints (atomic; one also at the end and on SIGINT/SIGTERM); "
        "0 = only at the end and on SIGINT/SIGTERM (a run killed otherwise resumes from the start)",
    )
    resume: str = _field(
        "output", "", "continue the run in this directory from its checkpoint, with its config"
    )
    tensorboard: bool = _field("output", True, "write TensorBoard event files to <run_dir>/tb")
    # --- physics backend
    physics: str = _field(
        "physics",
        "auto",
        "physics engine: " + ", ".join(PHYSICS) + " (auto = native MuJoCo on CPU for the envs that have it, "
        "else MJX; native envs: " + ", ".join(NATIVE_TASKS) + ")",
    )
    physics_threads: int = _field(
        "physics",
        DEFAULT_THREADS,
        "native physics: MuJoCo threads per step call, 0 = every core (see the bench physics suite)",
    )
    # --- exploration strategies and ablations
    coherent: CoherentOptions = dataclasses.field(
        default_factory=CoherentOptions,
        metadata={
            "group": "exploration",
            "help": "coherent ablations: coherent.integration=analytic|mc coherent.layers=last|all "
            "coherent.gradient=exact|episode|stored coherent.episode_restart=true|false",
        },
    )
    noisynet_sigma0: float = _field(
        "exploration",
        0.5,
        "noisynet: initial noise scale sigma_0; each layer's sigma starts at sigma_0 / sqrt(fan_in)",
    )
    gsde_resample_every: int = _field(
        "exploration",
        4,
        "gsde: steps between redraws of the noise matrix (also redrawn at each episode start)",
    )
    pink_exponent: float = _field(
        "exploration", 1.0, "pink: noise spectrum ~ 1/f^exponent (0 white, 1 pink, 2 red)"
    )
    # --- devices: sharding over JAX devices, several hosts
    num_devices: int = _field(
        "devices",
        0,
        "JAX devices to spread the envs (train) or the sweep points (sweep) over; 0 = all. "
        "num_envs must be a multiple of it",
    )
    distributed: bool = _field(
        "devices", False, "call jax.distributed.initialize() first (several hosts; see README, Devices)"
    )

    # --- derived (not settable)
    @property
    def steps_per_iteration(self) -> int:
        return self.num_envs * self.unroll_length

    @property
    def updates_per_iteration(self) -> int:
        """SAC: gradient updates per iteration, round(utd_ratio * steps_per_iteration)."""
        return int(round(self.utd_ratio * self.steps_per_iteration))

    @property
    def num_iterations(self) -> int:
        return max(1, math.ceil(self.total_steps / self.steps_per_iteration))


# Scalars that may differ across the points of one vmapped sweep: declared on their fields.
SWEEPABLE = tuple(f.name for f in dataclasses.fields(Config) if "sweep" in f.metadata)


def sweepable(key: str) -> Sweepable | None:
    """The `Sweepable` declaration of config key `key`, or None for a key a sweep cannot vary."""
    field = next((f for f in dataclasses.fields(Config) if f.name == key), None)
    return None if field is None else field.metadata.get("sweep")


class ConfigError(ValueError):
    """A bad override: unknown key, wrong type or value out of range."""


def _check(cond: bool, key: str, value: Any, allowed: str) -> None:
    if not cond:
        raise ConfigError(f"invalid value for {key!r}: {value!r} (allowed: {allowed})")


def validate(cfg: Config) -> Config:
    """Checks ranges and choices; raises `ConfigError` naming the first bad key."""
    _check(cfg.env in TASKS, "env", cfg.env, ", ".join(TASKS))
    if cfg.episode_length == 0:  # the task's registered time limit, written into the resolved config
        cfg = dataclasses.replace(cfg, episode_length=TASKS[cfg.env].episode_length)
    _check(cfg.algo in ALGOS, "algo", cfg.algo, ", ".join(ALGOS))
    _check(cfg.explore in EXPLORES, "explore", cfg.explore, ", ".join(EXPLORES))
    supported = SUPPORTED_ALGOS[cfg.explore]
    reason = REFUSED.get((cfg.explore, cfg.algo))
    _check(
        cfg.algo in supported,
        "algo",
        cfg.algo,
        f"{', '.join(supported)} with explore={cfg.explore}" + (f": {reason}" if reason else ""),
    )
    _validate_strategies(cfg)
    _check(
        cfg.coherent_inference in COHERENT_INFERENCE,
        "coherent_inference",
        cfg.coherent_inference,
        ", ".join(COHERENT_INFERENCE),
    )
    _check(cfg.activation in ACTIVATIONS, "activation", cfg.activation, ", ".join(ACTIVATIONS))
    for key in ("total_steps", "num_envs", "unroll_length", "episode_length", "num_epochs"):
        value = getattr(cfg, key)
        allowed = "an integer >= 1, or 0 for the task's own" if key == "episode_length" else "an integer >= 1"
        _check(1 <= value < 2**31, key, value, allowed)
    _check(0 <= cfg.seed <= limits.MAX_SEED, "seed", cfg.seed, limits.SEED_ALLOWED)
    _check(cfg.preset in NO_PRESET or cfg.preset in PRESETS, "preset", cfg.preset, ", ".join(PRESETS))
    cfg = dataclasses.replace(cfg, preset="") if cfg.preset in NO_PRESET else cfg
    _check(cfg.num_minibatches >= 1, "num_minibatches", cfg.num_minibatches, "an integer >= 1")
    _check(
        cfg.algo not in ON_POLICY or cfg.num_envs % cfg.num_minibatches == 0,
        "num_minibatches",
        cfg.num_minibatches,
        f"a divisor of num_envs={cfg.num_envs} (minibatches split envs)",
    )
    for key in (
        "lr",
        "clip_eps",
        "init_std",
        "action_std",
        "w_std_init",
        "temperature",
        "utd_ratio",
        "sigma_delta",
    ):
        value = getattr(cfg, key)
        _check(math.isfinite(value) and value > 0, key, value, "a finite number > 0")
    for key in ("gamma", "gae_lambda", "beta"):
        value = getattr(cfg, key)
        _check(math.isfinite(value) and 0.0 <= value <= 1.0, key, value, "a number in [0, 1]")
    for key in ("target_kl", "vf_coef", "ent_coef", "max_grad_norm", "vf_lr"):
        value = getattr(cfg, key)
        _check(math.isfinite(value) and value >= 0, key, value, "a finite number >= 0")
    separate = f"an integer >= 1 with vf_lr={cfg.vf_lr}" if cfg.vf_lr > 0 else "0 with vf_lr=0 (joint loss)"
    _check(cfg.vf_iters >= 0 and (cfg.vf_iters > 0) == (cfg.vf_lr > 0), "vf_iters", cfg.vf_iters, separate)
    for key in ("policy_hidden", "value_hidden"):
        value = list(getattr(cfg, key))
        _check(len(value) >= 1 and all(v >= 1 for v in value), key, value, "a list of ints >= 1")
    _check(cfg.buffer_size >= 1, "buffer_size", cfg.buffer_size, "an integer >= 1")
    _check(cfg.batch_size >= 1, "batch_size", cfg.batch_size, "an integer >= 1")
    _check(cfg.warmup_steps >= 0, "warmup_steps", cfg.warmup_steps, "an integer >= 0")
    after = cfg.update_after
    _check(after is None or 0 <= after < 2**31, "update_after", after, "an integer >= 0 or null")
    _check(math.isfinite(cfg.tau) and 0 < cfg.tau <= 1, "tau", cfg.tau, "a number in (0, 1]")
    _check(
        math.isfinite(cfg.sigma_init) and cfg.sigma_init >= 0,
        "sigma_init",
        cfg.sigma_init,
        "a finite number >= 0",
    )
    _check(
        math.isfinite(cfg.sigma_alpha) and cfg.sigma_alpha > 1, "sigma_alpha", cfg.sigma_alpha, "a number > 1"
    )
    if cfg.target_entropy is not None:
        _check(
            math.isfinite(cfg.target_entropy), "target_entropy", cfg.target_entropy, "a finite number or null"
        )
    if cfg.algo == "sac":
        _check(
            not cfg.normalize_rewards,
            "normalize_rewards",
            cfg.normalize_rewards,
            "false with algo=sac (reward scaling is a2c/ppo's)",
        )
        _check(
            cfg.buffer_size >= cfg.steps_per_iteration,
            "buffer_size",
            cfg.buffer_size,
            f"at least num_envs * unroll_length = {cfg.steps_per_iteration} (one iteration's data)",
        )
        _check(
            cfg.updates_per_iteration >= 1,
            "utd_ratio",
            cfg.utd_ratio,
            f"at least 1 / (num_envs * unroll_length) = {1 / cfg.steps_per_iteration:.3g}",
        )
    _check(cfg.physics in PHYSICS, "physics", cfg.physics, ", ".join(PHYSICS))
    _check(
        cfg.physics_threads >= 0, "physics_threads", cfg.physics_threads, "an integer >= 0 (0 = every core)"
    )
    _check(
        cfg.physics != "native" or cfg.env in NATIVE_TASKS,
        "env",
        cfg.env,
        "with physics=native: " + ", ".join(NATIVE_TASKS),
    )
    if cfg.physics == "mjx":
        try:
            resolve_physics(cfg.env, cfg.physics)
        except PhysicsError as exc:
            raise ConfigError(
                f"invalid value for 'physics': 'mjx' with env={cfg.env} ({exc}) (allowed: auto, native)"
            ) from None
    _check(cfg.eval_every >= 0, "eval_every", cfg.eval_every, "an integer >= 0")
    _check(cfg.eval_episodes >= 1, "eval_episodes", cfg.eval_episodes, "an integer >= 1")
    _check(cfg.checkpoint_every >= 0, "checkpoint_every", cfg.checkpoint_every, "an integer >= 0")
    _check(cfg.num_devices >= 0, "num_devices", cfg.num_devices, "an integer >= 0 (0 = all devices)")
    overflow = limits.counter_problem(cfg)
    if overflow is not None:
        _check(False, *overflow)
    return cfg


def _validate_strategies(cfg: Config) -> None:
    """Checks the settings of the strategies and ablations, and the pairs they refuse."""
    co = cfg.coherent
    _check(
        co.integration in COHERENT_INTEGRATION,
        "coherent.integration",
        co.integration,
        ", ".join(COHERENT_INTEGRATION),
    )
    _check(co.layers in COHERENT_LAYERS, "coherent.layers", co.layers, ", ".join(COHERENT_LAYERS))
    _check(co.gradient in COHERENT_GRADIENT, "coherent.gradient", co.gradient, ", ".join(COHERENT_GRADIENT))
    if cfg.explore == "coherent":
        _check(
            co.gradient != "episode" or cfg.coherent_inference == "joint",
            "coherent_inference",
            cfg.coherent_inference,
            "joint with coherent.gradient=episode (the loss re-infers the episode prefix in joint form)",
        )
        _check(
            co.episode_restart or co.gradient != "episode",
            "coherent.episode_restart",
            co.episode_restart,
            "true with coherent.gradient=episode (the prefix it re-infers starts at the episode start)",
        )
        _check(
            co.episode_restart or (cfg.algo in ON_POLICY and co.integration == "analytic"),
            "coherent.episode_restart",
            co.episode_restart,
            "true with algo=sac or coherent.integration=mc (the switch is the analytic chain's)",
        )
        _check(
            cfg.algo in ON_POLICY or co.integration == "mc",
            "coherent.integration",
            co.integration,
            "mc with algo=sac: analytic integration needs an on-policy algorithm "
            "(SAC never scores its behaviour actions)",
        )
        _check(
            co.layers == "last" or co.integration == "mc",
            "coherent.integration",
            co.integration,
            "mc with coherent.layers=all: only the last layer integrates analytically",
        )
        _check(
            co.layers == "last" or cfg.algo in ON_POLICY,
            "coherent.layers",
            co.layers,
            "last with algo=sac: Coherent-SAC perturbs the actor's mean head (thesis §4.3); "
            "every-layer noise for SAC is explore=psne",
        )
    _check(
        math.isfinite(cfg.noisynet_sigma0) and cfg.noisynet_sigma0 > 0,
        "noisynet_sigma0",
        cfg.noisynet_sigma0,
        "a finite number > 0",
    )
    _check(
        1 <= cfg.gsde_resample_every < 2**31,
        "gsde_resample_every",
        cfg.gsde_resample_every,
        "an integer >= 1",
    )
    _check(
        math.isfinite(cfg.pink_exponent) and 0 <= cfg.pink_exponent <= 4,
        "pink_exponent",
        cfg.pink_exponent,
        "a number in [0, 4] (0 white, 1 pink, 2 red)",
    )
    if cfg.explore == "pink":
        _check(
            cfg.episode_length >= 2,
            "episode_length",
            cfg.episode_length,
            "an integer >= 2 with explore=pink (one noise sequence per episode)",
        )


def _group_fields() -> dict[str, set[str]]:
    """Config fields that are dataclass groups (``coherent``) -> their sub-keys."""
    return {
        f.name: {g.name for g in dataclasses.fields(f.default_factory)}
        for f in dataclasses.fields(Config)
        if f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory)
    }


def parse_overrides(overrides: Sequence[str], base: Config | None = None) -> Config:
    """Builds a validated `Config` from ``key=value`` strings (Hydra/OmegaConf syntax).

    Lists are written ``policy_hidden=[64,64]``. Raises `ConfigError` with a
    one-line message for a malformed override, an unknown key, a value of the
    wrong type or out of range. The defaults of the chosen algorithm
    (`presets.ALGO_DEFAULTS`) apply first, then the chosen preset's values for it, then the
    overrides (`coherent_jax.presets.layered_base`): ``algo=sac num_envs=4`` keeps
    SAC's network sizes and takes the user's env count.
    """
    groups = _group_fields()
    known = {f.name for f in dataclasses.fields(Config)} - set(groups)
    known |= {f"{g}.{k}" for g, keys in groups.items() for k in keys}
    chosen: dict[str, str | None] = {"algo": None, "preset": None}
    for item in overrides:
        if "=" not in item or item.startswith("="):
            raise ConfigError(f"malformed override {item!r}: expected key=value")
        key = item.split("=", 1)[0].strip()
        if key not in known:
            raise ConfigError(f"unknown key {key!r}; valid keys: {', '.join(sorted(known))}")
        _check_yaml(key, item.split("=", 1)[1])
        if key in chosen:
            chosen[key] = item.split("=", 1)[1].strip()
    base = layered_base(base if base is not None else Config(), **chosen)
    schema = OmegaConf.structured(base)
    try:
        merged = OmegaConf.merge(schema, OmegaConf.from_dotlist(list(overrides)))
        cfg = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or "?"
        owner, name = (Config, key) if "." not in key else (getattr(Config(), key.split(".")[0]), key)
        name = name.rsplit(".", 1)[-1]
        field = next((f for f in dataclasses.fields(owner) if f.name == name), None)
        expected = _type_name(field.type) if field is not None else "a valid value"
        if key in _choices():
            expected = ", ".join(_choices()[key])
        msg = str(exc).splitlines()[0]
        raise ConfigError(f"invalid value for {key!r}: {msg} (allowed: {expected})") from None
    return validate(cfg)


def _check_yaml(key: str, text: str) -> None:
    """Raises `ConfigError` naming `key` if its value is not valid YAML (``[64,64``, ``{``)."""
    import yaml

    try:
        yaml.safe_load(text)
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or "malformed"
        raise ConfigError(
            f"invalid value for {key!r}: {text.strip()!r} is not valid YAML ({problem}) "
            f"(allowed: a YAML scalar or a list such as [64,64])"
        ) from None


def _choices() -> dict[str, tuple[str, ...]]:
    """The keys whose value is one name of a list, and that list (an error message shows it)."""
    return {
        "env": tuple(TASKS),
        "algo": ALGOS,
        "explore": EXPLORES,
        "activation": ACTIVATIONS,
        "coherent_inference": COHERENT_INFERENCE,
        "physics": tuple(PHYSICS),
        "coherent.integration": COHERENT_INTEGRATION,
        "coherent.layers": COHERENT_LAYERS,
        "coherent.gradient": COHERENT_GRADIENT,
    }


def _type_name(tp: Any) -> str:
    return {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string"}.get(
        str(tp), str(tp)
    )


def to_dict(cfg: Config) -> dict[str, Any]:
    """Plain-dict view of the config (for the run directory)."""
    return dataclasses.asdict(cfg)


def help_text() -> str:
    """Every option with its default and a one-line description, grouped."""
    lines = ["usage: python -m coherent_jax.train [key=value ...]", "", *help_lines()]
    lines.append(f"sweepable (a list runs a grid with coherent_jax.sweep): {', '.join(SWEEPABLE)}")
    for group in GROUPS:
        lines += ["", f"{group}:"]
        for f in dataclasses.fields(Config):
            if f.metadata.get("group") != group:
                continue
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            if isinstance(default, list):
                default = "[" + ",".join(str(v) for v in default) + "]"
            lines.append(f"  {f.name}={default}".ljust(34) + f"  {f.metadata.get('help', '')}")
            if dataclasses.is_dataclass(default):
                for g in dataclasses.fields(default):
                    value = getattr(default, g.name)
                    lines.append(f"  {f.name}.{g.name}={value}".ljust(34) + f"  {g.metadata.get('help', '')}")
    return "\n".join(lines)

"""The configuration: shared settings at the top level, the rest in groups.

Settings every run reads (the task, the budget, the env count, the learning rate,
the networks, the output...) are top-level fields; an algorithm's or a strategy's own
settings are a group (`coherent_jax.config.groups`: ``ppo.*``, ``sac.*``,
``coherent.*``, ``coherent_sac.*``, ``noisynet.*``, ``psne.*``, ``gsde.*``, ``pink.*``,
``lattice.*``). Every field declares its help, range or choices
(`coherent_jax.config.declare`); the keys of before are `coherent_jax.config.legacy`'s.
No JAX here.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from coherent_jax.config import limits
from coherent_jax.config.declare import (
    COUNT,
    EVERY,
    LAYERS,
    POSITIVE,
    UNIT,
    Sweepable,
    at_least,
    field,
    sweep,
)
from coherent_jax.config.groups import (
    CoherentOptions,
    CoherentSACOptions,
    GsdeOptions,
    LatticeOptions,
    NoisyNetOptions,
    PinkOptions,
    PPOOptions,
    PsneOptions,
    SACOptions,
)
from coherent_jax.config.presets import NO_PRESET, PRESETS
from coherent_jax.envs.registry import DEFAULT_THREADS, NATIVE_TASKS, PHYSICS, TASKS, USER_TASK_FORM
from coherent_jax.strategies import ALGOS, EXPLORES

ACTIVATIONS = ("tanh", "relu", "elu", "swish")
# The registry's tasks or a user's (checked by `coherent_jax.config.checks.task_spec`).
ENV_ALLOWED = ", ".join(TASKS) + ", or " + USER_TASK_FORM


def _group(cls: type, help: str) -> Any:
    return dataclasses.field(default_factory=cls, metadata={"help": help, "group": None})


@dataclasses.dataclass
class Config:
    """Everything that defines a training run (see ``--help``)."""

    # --- what to run
    # Checked first by `validate` (a MODULE:NAME task is not a fixed choice).
    env: str = field("halfcheetah", "task name: " + ENV_ALLOWED, group="run", allowed=ENV_ALLOWED)
    algo: str = field("ppo", "algorithm: " + ", ".join(ALGOS), group="run", choices=ALGOS)
    explore: str = field(
        "action", "exploration strategy: " + ", ".join(EXPLORES), group="run", choices=EXPLORES
    )
    preset: str | None = field(
        "",
        "a protocol's values over the algo's defaults: " + ", ".join(PRESETS),
        group="run",
        choices=(*NO_PRESET, *PRESETS),
    )
    seed: int = field(
        0,
        "PRNG seed; the same seed gives the same run",
        group="run",
        check=(lambda v: 0 <= v <= limits.MAX_SEED, limits.SEED_ALLOWED),
    )
    total_steps: int = field(
        2_000_000,
        "environment steps to train for, rounded up to whole iterations of num_envs * unroll_length",
        group="run",
        check=COUNT,
    )
    # --- collection
    num_envs: int = field(64, "parallel environments", group="collection", check=COUNT)
    unroll_length: int = field(
        64, "steps per env per iteration (segment length T)", group="collection", check=COUNT
    )
    episode_length: int = field(
        0,
        "time limit in env steps (truncation is bootstrapped); 0 = the task's own (1000; reacher 50)",
        group="collection",
        check=at_least(1, "an integer >= 1, or 0 for the task's own", below=2**31),
    )
    # --- optimisation (every algorithm)
    lr: float = field(
        3e-4,
        "Adam learning rate (policy and value)",
        group="optimisation",
        check=POSITIVE,
        sweep=sweep(EVERY),
    )
    gamma: float = field(0.99, "discount factor", group="optimisation", check=UNIT, sweep=sweep(EVERY))
    normalize_obs: bool = field(True, "running mean/std observation normalisation", group="optimisation")
    # --- networks
    policy_hidden: list[int] = field([64, 64], "policy trunk layer sizes", group="networks", check=LAYERS)
    value_hidden: list[int] = field([64, 64], "value network layer sizes", group="networks", check=LAYERS)
    activation: str = field(
        "tanh", "hidden activation: " + ", ".join(ACTIVATIONS), group="networks", choices=ACTIVATIONS
    )
    # --- exploration (every strategy with a Gaussian policy)
    init_std: float = field(
        0.5,
        "action, noisynet, psne, gsde, pink: initial std of the Gaussian policy",
        group="exploration",
        check=POSITIVE,
    )
    # --- evaluation and output
    eval_every: int = field(
        10,
        "iterations between deterministic evaluations; 0 = only at the end",
        group="output",
        check=at_least(0),
    )
    eval_episodes: int = field(
        8, "episodes per evaluation (run in parallel)", group="output", check=at_least(1)
    )
    run_dir: str = field(
        "", "output directory; default runs/<env>-<algo>-<explore>-s<seed>-<time>", group="output"
    )
    progress: bool = field(True, "show a progress bar", group="output")
    checkpoint_every: int = field(
        10,
        "iterations between checkpoints (atomic; one also at the end and on SIGINT/SIGTERM); "
        "0 = only at the end and on SIGINT/SIGTERM (a run killed otherwise resumes from the start)",
        group="output",
        check=at_least(0),
    )
    resume: str = field(
        "", "continue the run in this directory from its checkpoint, with its config", group="output"
    )
    tensorboard: bool = field(True, "write TensorBoard event files to <run_dir>/tb", group="output")
    wandb: bool = field(
        False,
        "mirror the run to Weights & Biases, offline unless WANDB_MODE is set "
        '(pip install -e ".[wandb]"; docs/runs.md)',
        group="output",
    )
    wandb_init_timeout: float = field(
        30.0,
        "seconds W&B may take to start its run (WANDB_MODE=online: reach the server) before "
        "the run is refused",
        group="output",
        check=POSITIVE,
    )
    # --- physics backend
    physics: str = field(
        "auto",
        "physics engine: " + ", ".join(PHYSICS) + " (auto = native MuJoCo on CPU for the envs that have it, "
        "else MJX; native envs: " + ", ".join(NATIVE_TASKS) + ")",
        group="physics",
        choices=PHYSICS,
    )
    physics_threads: int = field(
        DEFAULT_THREADS,
        "native physics: MuJoCo threads per step call, 0 = every core (see the bench physics suite)",
        group="physics",
        check=at_least(0, "an integer >= 0 (0 = every core)"),
    )
    # --- devices: sharding over JAX devices, several hosts
    num_devices: int = field(
        0,
        "JAX devices to spread the envs (train) or the sweep points (sweep) over; 0 = all. "
        "num_envs must be a multiple of it",
        group="devices",
        check=at_least(0, "an integer >= 0 (0 = all devices)"),
    )
    distributed: bool = field(
        False,
        "call jax.distributed.initialize() first (several hosts; see docs/runs.md, Devices)",
        group="devices",
    )
    # --- the groups: an algorithm's or a strategy's own settings
    ppo: PPOOptions = _group(PPOOptions, "a2c and ppo")
    sac: SACOptions = _group(SACOptions, "sac")
    coherent: CoherentOptions = _group(CoherentOptions, "explore=coherent")
    coherent_sac: CoherentSACOptions = _group(CoherentSACOptions, "algo=sac explore=coherent")
    noisynet: NoisyNetOptions = _group(NoisyNetOptions, "explore=noisynet")
    psne: PsneOptions = _group(PsneOptions, "explore=psne")
    gsde: GsdeOptions = _group(GsdeOptions, "explore=gsde")
    pink: PinkOptions = _group(PinkOptions, "explore=pink")
    lattice: LatticeOptions = _group(LatticeOptions, "explore=lattice")

    # --- derived (not settable)
    @property
    def steps_per_iteration(self) -> int:
        return self.num_envs * self.unroll_length

    @property
    def updates_per_iteration(self) -> int:
        """SAC: gradient updates per iteration, round(utd_ratio * steps_per_iteration)."""
        return int(round(self.sac.utd_ratio * self.steps_per_iteration))

    @property
    def num_iterations(self) -> int:
        return max(1, math.ceil(self.total_steps / self.steps_per_iteration))


# Help sections of the top-level fields, in the order ``--help`` prints them; the groups follow.
SECTIONS = ("run", "collection", "optimisation", "networks", "exploration", "output", "physics", "devices")
# The groups: a config field holding a dataclass of its own settings.
GROUPS: tuple[str, ...] = tuple(
    f.name for f in dataclasses.fields(Config) if dataclasses.is_dataclass(f.default_factory)
)


def _fields() -> dict[str, dataclasses.Field]:
    """Every settable key -> its field: top-level names, a group's dotted (``coherent.beta``)."""
    out: dict[str, dataclasses.Field] = {}
    for f in dataclasses.fields(Config):
        if f.name in GROUPS:
            out.update({f"{f.name}.{g.name}": g for g in dataclasses.fields(f.default_factory)})
        else:
            out[f.name] = f
    return out


FIELDS: dict[str, dataclasses.Field] = _fields()
# Scalars that may differ across the points of one vmapped sweep: declared on their fields.
SWEEPABLE: tuple[str, ...] = tuple(k for k, f in FIELDS.items() if "sweep" in f.metadata)


def sweepable(key: str) -> Sweepable | None:
    """The `Sweepable` declaration of config key `key`, or None for a key a sweep cannot vary."""
    field = FIELDS.get(key)
    return None if field is None else field.metadata.get("sweep")


def hparam_path(key: str) -> tuple[str, ...]:
    """The field path of sweepable `key` in the trainer's hyperparameters (its last part
    unless declared), e.g. ``("explore", "beta")`` for ``coherent.beta``."""
    return tuple((sweepable(key).hparam or key.rsplit(".", 1)[-1]).split("."))


def get_value(cfg: Config, key: str) -> Any:
    """The value of `key` (dotted for a group's) in `cfg`."""
    group, _, name = key.rpartition(".")
    return getattr(getattr(cfg, group) if group else cfg, name)


def with_values(cfg: Config, values: dict[str, Any]) -> Config:
    """`cfg` with `values` (keys dotted for a group's), other fields shared."""
    top = {k: v for k, v in values.items() if "." not in k}
    for group in {k.split(".")[0] for k in values if "." in k}:
        sub = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith(group + ".")}
        top[group] = dataclasses.replace(getattr(cfg, group), **sub)
    return dataclasses.replace(cfg, **top)

"""The configuration: shared settings at the top level, the rest in groups; its defaults in layers.

Settings every run reads (the task, the budget, the env count, the learning rate,
the networks, the output...) are top-level fields; an algorithm's or a strategy's own
settings are a group (`coherent_jax.config.groups`: ``ppo.*``, ``sac.*``,
``coherent.*``, ``coherent_sac.*``, ``noisynet.*``, ``psne.*``, ``gsde.*``, ``pink.*``,
``lattice.*``). Every field declares its help, range or choices
(`coherent_jax.config.groups`); the keys of before are `coherent_jax.config.parse`'s.

Defaults that depend on the algorithm, and named protocols (``preset=NAME``): a
configuration is built in layers, each over the one before:

1. `Config`'s defaults;
2. `ALGO_DEFAULTS` of the chosen algorithm;
3. the chosen preset's values for that algorithm (`PRESETS`);
4. the user's ``key=value`` overrides (the user wins).

A layer is applied when its choice is made: a stored config (a run being resumed)
already holds every value, so nothing is applied over it again (`layered_base`).

``preset=thesis`` is the protocol of "Deep Coherent Exploration for Continuous
Control" (Zhang and van Hoof, ICML 2021), whose implementation base is OpenAI Spinning
Up: Spinning Up's documented defaults for PPO (``spinup/algos/pytorch/ppo/ppo.py``),
VPG (A2C here, ``vpg/vpg.py``) and SAC (``sac/sac.py``). ``docs/presets.md`` gives
each value, its source and where this library differs.

Seeds: a run's PRNG key is ``jax.random.PRNGKey(seed)`` (`coherent_jax.run.loop.run_keys`).
With 32-bit JAX (the default, ``jax_enable_x64`` off) it takes the seed's low 32 bits,
so seeds 0 and 2**32 give the same key, and a seed of 2**63 or more does not convert
at all (OverflowError). The seeds that give distinct keys are [0, `MAX_SEED`]; what the
int32 counters hold is checked with the config (`coherent_jax.config.checks.counter_problem`).

No JAX here: ``--help`` and the config parser read these tables.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from coherent_jax.config.groups import (
    COUNT,
    EVERY,
    LAYERS,
    POSITIVE,
    UNIT,
    CoherentOptions,
    CoherentSACOptions,
    GsdeOptions,
    LatticeOptions,
    NoisyNetOptions,
    PinkOptions,
    PPOOptions,
    PsneOptions,
    SACOptions,
    Sweepable,
    at_least,
    field,
    sweep,
)
from coherent_jax.envs.registry import DEFAULT_THREADS, NATIVE_TASKS, PHYSICS, TASKS, USER_TASK_FORM
from coherent_jax.strategies import ALGOS, EXPLORES

ACTIVATIONS = ("tanh", "relu", "elu", "swish")
# The registry's tasks or a user's (checked by `coherent_jax.config.checks.task_spec`).
ENV_ALLOWED = ", ".join(TASKS) + ", or " + USER_TASK_FORM
# The seeds that give distinct PRNG keys (the module's docstring, "Seeds").
MAX_SEED = 2**32 - 1
SEED_ALLOWED = f"an integer in [0, {MAX_SEED}]: the PRNG key is derived from the seed's 32 bits"


# ------------------------------------------------------------------ the layers of defaults
# Defaults that differ by algorithm (applied before the preset and the user's overrides):
# SAC's networks, batch and env count follow Haarnoja et al. 2018 / CleanRL rather than PPO.
ALGO_DEFAULTS: dict[str, dict[str, Any]] = {
    "sac": {
        "total_steps": 300_000,
        "num_envs": 8,
        "unroll_length": 16,
        "lr": 3e-4,
        "policy_hidden": [256, 256],
        "value_hidden": [256, 256],
        "activation": "relu",
        "normalize_obs": False,
        "eval_every": 20,
        # A checkpoint holds the replay buffer (1M transitions: 170 MB per seed on
        # HalfCheetah). Every 10 iterations of 128 steps, writing it took longer than the
        # training between (a 5-seed sweep at UTD 0.25: 12-17 s stalls every 1,280
        # steps, 45% of the wall time); every 200 it is a few percent.
        "checkpoint_every": 200,
        # Coherent-SAC uses the sampled w_t (thesis §4.3): there is no log-prob to integrate.
        "coherent": {"integration": "mc"},
    },
}

# Spinning Up's PPO and VPG share the buffer, GAE, networks and the value function's
# own optimiser (ppo.py / vpg.py: steps_per_epoch=4000, gamma=0.99, lam=0.97,
# pi_lr=3e-4, vf_lr=1e-3, train_v_iters=80, MLPActorCritic (64, 64) tanh, log_std -0.5).
_THESIS_ON_POLICY: dict[str, Any] = {
    "num_envs": 4,  # 4 x 1000 = steps_per_epoch 4000 (ppo.py's __main__ runs --cpu 4 of 1000)
    "unroll_length": 1000,
    "gamma": 0.99,
    "lr": 3e-4,  # pi_lr
    "normalize_obs": False,
    "policy_hidden": [64, 64],
    "value_hidden": [64, 64],
    "activation": "tanh",
    "init_std": math.exp(-0.5),  # MLPGaussianActor: log_std = -0.5
    # The chain is drawn at the buffer's start and runs through it across resets.
    "coherent": {"episode_restart": False},
}
_THESIS_PPO_GROUP: dict[str, Any] = {
    "gae_lambda": 0.97,
    "vf_lr": 1e-3,
    "vf_iters": 80,  # train_v_iters
    "ent_coef": 0.0,
    "max_grad_norm": 0.0,  # no gradient clipping
    "normalize_advantages": True,  # over the whole buffer (PPOBuffer.get)
    "normalize_rewards": False,
}

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "thesis": {
        "ppo": {
            **_THESIS_ON_POLICY,
            "ppo": {
                **_THESIS_PPO_GROUP,
                "clip_eps": 0.2,  # clip_ratio
                "num_epochs": 80,  # train_pi_iters, full batch, early stopped
                "num_minibatches": 1,
                "target_kl": 0.01,
            },
        },
        # VPG: one policy step
        "a2c": {**_THESIS_ON_POLICY, "ppo": {**_THESIS_PPO_GROUP, "num_epochs": 1, "num_minibatches": 1}},
        "sac": {
            "num_envs": 1,
            "unroll_length": 50,  # update_every
            "lr": 1e-3,
            "gamma": 0.99,
            "sac": {
                "utd_ratio": 1.0,  # update_every updates every update_every steps
                "tau": 0.005,  # polyak 0.995
                "temperature": 0.2,  # alpha
                "auto_temperature": False,
                "batch_size": 100,
                "buffer_size": 1_000_000,  # replay_size
                "warmup_steps": 10_000,  # start_steps
                "update_after": 1_000,
            },
            "policy_hidden": [256, 256],
            "value_hidden": [256, 256],
            "activation": "relu",
            "normalize_obs": False,
            "eval_every": 80,  # every 4000 steps (steps_per_epoch) ...
            "eval_episodes": 10,  # ... num_test_episodes
        },
    },
    # Many envs, large batches, fewer updates per env step (in the style of FastSAC and
    # FastTD3; docs/presets.md): per iteration 512 env steps and 32 updates of 1,024
    # transitions, where algo=sac's defaults take 128 steps and 128 updates of 256. The
    # same gradient work per iteration (32 x 1,024 = 128 x 256 samples) over 4x the steps.
    "fast_sac": {
        "sac": {
            "num_envs": 64,
            "unroll_length": 8,
            "sac": {"batch_size": 1024, "utd_ratio": 0.0625},
            "eval_every": 10,  # every 5,120 env steps (algo=sac: every 2,560)
            "checkpoint_every": 100,  # every 51,200 env steps
        },
    },
}
PRESET_DESCRIPTIONS = {
    "thesis": "the thesis's protocol, OpenAI Spinning Up's defaults (docs/presets.md)",
    "fast_sac": (
        "algo=sac only: 64 envs, batch 1024, 1/16 update per env step; loses on a CPU (docs/presets.md)"
    ),
}
# Values of ``preset`` that select no preset (``preset=`` is null); a config records "".
NO_PRESET = ("", "none", "null", None)


# ------------------------------------------------------------------ the config
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
        check=(lambda v: 0 <= v <= MAX_SEED, SEED_ALLOWED),
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


# ------------------------------------------------------------------ applying the layers
def apply_layer(base: Any, changes: dict[str, Any]) -> Any:
    """`base` (a config dataclass) with `changes`; a dict value updates that group's fields."""
    changes = dict(changes)
    for key, value in changes.items():
        if isinstance(value, dict):
            changes[key] = dataclasses.replace(getattr(base, key), **value)
        elif isinstance(value, list):
            changes[key] = list(value)
    return dataclasses.replace(base, **changes)


def layered_base(base: Any, algo: str | None, preset: str | None) -> Any:
    """`base` with the layers of the choices the overrides make (`algo`, `preset`: None if not given).

    A choice equal to the base's own applies nothing: the base (a stored config, say)
    already holds its layers, and the user's values over them. Choosing another algorithm
    applies its `ALGO_DEFAULTS` and, if a preset is in force, the preset's values for it.
    """
    new_algo = algo is not None and algo != base.algo
    new_preset = preset is not None and preset != base.preset
    algo = algo if algo is not None else base.algo
    preset = preset if preset is not None else base.preset
    if new_algo and algo in ALGO_DEFAULTS:
        base = apply_layer(base, ALGO_DEFAULTS[algo])
    if (new_algo or new_preset) and preset not in NO_PRESET and algo in PRESETS.get(preset, {}):
        base = apply_layer(base, PRESETS[preset][algo])
    return base


def dotted_items(values: dict[str, Any]) -> dict[str, Any]:
    """A layer's values with a group's fields as dotted keys (``{"ppo": {"clip_eps": 0.2}}`` ->
    ``{"ppo.clip_eps": 0.2}``)."""
    items: dict[str, Any] = {}
    for k, v in values.items():
        items.update({f"{k}.{g}": w for g, w in v.items()} if isinstance(v, dict) else {k: v})
    return items


def _flat(values: dict[str, Any], same: Any = None) -> str:
    """``key=value`` items of a layer, a group's fields dotted (``ppo.clip_eps=0.2``); an item for
    which ``same(key, value)`` is true is left out."""
    items = {k: v for k, v in dotted_items(values).items() if same is None or not same(k, v)}
    shown = {k: str(v).lower() if isinstance(v, bool) else v for k, v in items.items()}
    return " ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in shown.items()).replace(
        ", ", ","
    )


def help_lines(same_as_default: Any = None) -> list[str]:
    """What ``--help`` says about the algorithm defaults and every preset, per algorithm.

    ``same_as_default(key, value)``: whether an algorithm's default equals the base default
    (it changes nothing, so it is not listed as a change)."""
    lines = [
        f"algo={algo} changes these defaults: {_flat(values, same_as_default)}"
        for algo, values in ALGO_DEFAULTS.items()
    ]
    for name, per_algo in PRESETS.items():
        lines.append(f"preset={name}: {PRESET_DESCRIPTIONS[name]}; over the algo's defaults it sets")
        lines += [f"  with algo={algo}: {_flat(values)}" for algo, values in per_algo.items()]
    return lines

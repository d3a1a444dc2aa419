"""The checkpoint and the stored config a resume checks it against: ``checkpoint.msgpack``
and ``config.yaml``, and how a resume reads them (`resume_config`, `resume_point`).

A checkpoint is one file, ``checkpoint.msgpack``, replaced atomically (written to a
temporary file, flushed to disk, then renamed over the old one), so a run killed at
any moment leaves either the previous checkpoint or the new one, never a mixture.
It is a msgpack map (flax serialisation, never pickle) of

* ``meta``: JSON text: format tag, the config fingerprint, the iteration, the env
  steps and the run loop's own state (evaluation PRNG key, timers, last metrics);
* ``state``: the leaves of the trainer's whole state pytree
  (`coherent_jax.run.devices.state_to_bytes`);
* ``host``, only in a run of a Gymnasium env (``env=gym:ID`` or the user's ``gymnasium.Env``):
  the state of the envs on the host, which the trainer's state cannot hold
  (`coherent_jax.envs.host_gym.HostPool.snapshot`: each env pickled with its random
  generator, and a MuJoCo env's full ``MjData`` physics state and solver warm start), so a
  resumed run steps on bit for bit. It is the one pickled entry: it is read only when the
  run's own checkpoint is resumed, after the digest has been verified;
* ``sha256``: digest of ``meta``, ``state`` (and ``host``), so truncation or corruption is
  detected before anything is restored.

The fingerprint is a hash of every config field that changes what a run computes
(all but `RESUMABLE_KEYS`); resuming with a different config or from another run's
directory is refused, naming the first key that differs. ``total_steps`` is not
part of it: a run (or a sweep) may be resumed with a larger budget to extend it.
A checkpoint holds one state pytree, a single run's or a sweep's stacked one.

The rest of the run directory (rows, lock, versions) is `coherent_jax.run.rundir`'s; the
state's bytes need JAX (`coherent_jax.run.devices.state_to_bytes`, `restore_state`), this
module does not: ``--help``, bad input and dry runs read it without JAX.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import msgpack
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from coherent_jax.config import Config, ConfigError, from_stored, parse_overrides, to_dict, validate
from coherent_jax.config.parse import flat_dict, modern_key
from coherent_jax.run.rundir import CONFIG, METRICS, atomic_write, read_metrics

CHECKPOINT = "checkpoint.msgpack"
PARAMS = "params.msgpack"  # a finished run's final parameters (`coherent_jax.policy.net`)
FORMAT = "coherent_jax-checkpoint-1"
# Fields that may differ between a run and its resumption: they change where and how
# a run reports, or how long it goes on, never what its iterations compute.
RESUMABLE_KEYS = (
    "run_dir",
    "progress",
    "resume",
    "checkpoint_every",
    "tensorboard",
    "wandb",
    "wandb_init_timeout",
    "total_steps",
)
# Before total_steps became resumable it was fingerprinted: such checkpoints still
# resume, at their own budget. (``wandb`` and ``wandb_init_timeout`` came later, never
# fingerprinted.)
_LEGACY_RESUMABLE_KEYS = tuple(k for k in RESUMABLE_KEYS if k != "total_steps")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: missing, truncated, corrupted or from another run."""


def fingerprint_fields(cfg: Config, resumable: tuple[str, ...] = RESUMABLE_KEYS) -> dict[str, Any]:
    """The config fields a checkpoint must agree with (all but `RESUMABLE_KEYS`), in the flat
    layout of before the config's groups (`config.parse.flat_dict`): a checkpoint written
    then, under the keys of before, has the same fingerprint now."""
    return {k: v for k, v in flat_dict(cfg).items() if k not in resumable}


def config_fingerprint(cfg: Config, resumable: tuple[str, ...] = RESUMABLE_KEYS) -> str:
    """sha256 of the fields of `fingerprint_fields`, as canonical JSON."""
    text = json.dumps(fingerprint_fields(cfg, resumable), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def config_difference(a: Config, b: Config) -> str | None:
    """The first fingerprinted key where `a` and `b` differ, or None."""
    fa, fb = fingerprint_fields(a), fingerprint_fields(b)
    for key in fa:
        if fa[key] != fb.get(key):
            return modern_key(key, note=False, pair=(a.algo, a.explore))
    return None


def load_config(run_dir: Path) -> Config:
    """The validated `Config` stored in ``run_dir/config.yaml``.

    Raises `ConfigError` (one line) for a missing file, a malformed YAML, an unknown
    key or a bad value (a NaN learning rate, say), naming the file and the key.
    """
    path = Path(run_dir) / CONFIG
    if not path.is_file():
        raise ConfigError(
            f"invalid run directory {str(run_dir)!r}: no {CONFIG} (allowed: a training run's directory)"
        )
    try:
        stored = yaml.safe_load(path.read_text())
        if not isinstance(stored, dict) or not stored:
            shape = "empty" if not stored else f"a YAML {type(stored).__name__}, not a mapping"
            raise ConfigError(f"invalid {path}: {shape} (allowed: a mapping of the run's config keys)")
        cfg = from_stored(stored)  # a flat config of before too
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "malformed"
        raise ConfigError(f"invalid {path}: not valid YAML{where} ({problem})") from None
    except ConfigError:
        raise
    except (OmegaConfBaseException, ValueError, TypeError, OSError) as exc:
        key = getattr(exc, "full_key", None) or "?"
        raise ConfigError(f"invalid {path}: key {key!r}: {str(exc).splitlines()[0]}") from None
    try:
        return validate(cfg)
    except ConfigError as exc:
        raise ConfigError(f"invalid {path}: {exc}") from None


def stored_config(cfg: Config) -> dict[str, Any]:
    """The run's resolved config as ``config.yaml`` records it (and W&B logs it): without
    ``resume``, which says how a session began."""
    return to_dict(dataclasses.replace(cfg, resume=""))


def config_text(cfg: Config) -> str:
    """The text of ``config.yaml`` for `cfg` (`stored_config` as YAML)."""
    return OmegaConf.to_yaml(stored_config(cfg))


def write_config(run_dir: Path, cfg: Config) -> None:
    """The run's resolved config as ``config.yaml`` (`config_text`)."""
    atomic_write(run_dir / CONFIG, config_text(cfg).encode())


@dataclasses.dataclass
class LoopState:
    """What the run loop itself carries between iterations (besides the trainer state).

    A single run stores scalars; a sweep stores one entry per grid point (lists).

    Attributes:
      eval_key: the loop's PRNG key for evaluations (two uint32 words; per point in a sweep).
      train_s, eval_s, elapsed_s: seconds spent so far (reported, never compared).
      last_return: latest finite training-episode return (NaN before any).
      last_eval: metrics of the latest evaluation.
      diverged: sweep points that diverged (index as text -> the reason); their rows stop.
    """

    eval_key: list[Any]
    train_s: float = 0.0
    eval_s: float = 0.0
    elapsed_s: float = 0.0
    last_return: Any = float("nan")
    last_eval: dict[str, Any] = dataclasses.field(default_factory=dict)
    diverged: dict[str, str] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class Checkpoint:
    """A verified checkpoint: its metadata and the raw state bytes."""

    iteration: int
    env_steps: int
    fingerprint: str
    loop: LoopState
    state_bytes: bytes
    host: bytes | None = None


def _json_safe(x: Any) -> Any:
    """Non-finite floats as None (JSON has no NaN), in nested lists too."""
    if isinstance(x, list):
        return [_json_safe(v) for v in x]
    return x if math.isfinite(x) else None


def _from_json(x: Any) -> Any:
    if isinstance(x, list):
        return [_from_json(v) for v in x]
    return float("nan") if x is None else x


def encode_checkpoint(
    cfg: Config,
    iteration: int,
    env_steps: int,
    loop: LoopState,
    state_bytes: bytes,
    host: bytes | None = None,
) -> bytes:
    """The bytes of ``checkpoint.msgpack`` (see the module docstring); ``host``, the host envs' state."""
    loop_dict = dataclasses.asdict(loop)
    loop_dict["last_return"] = _json_safe(loop.last_return)
    loop_dict["last_eval"] = {k: _json_safe(v) for k, v in loop.last_eval.items()}
    meta = json.dumps(
        {
            "format": FORMAT,
            "fingerprint": config_fingerprint(cfg),
            "iteration": int(iteration),
            "env_steps": int(env_steps),
            "loop": loop_dict,
        },
        sort_keys=True,
    ).encode()
    digest = hashlib.sha256(meta + state_bytes + (host or b"")).hexdigest()
    record = {"meta": meta, "state": state_bytes, "sha256": digest}
    if host is not None:
        record["host"] = host
    return msgpack.packb(record, use_bin_type=True)


def decode_checkpoint(path: Path, cfg: Config) -> Checkpoint:
    """Reads and verifies ``path`` against `cfg`; raises `CheckpointError` in one line.

    Nothing is written or changed, whatever the outcome.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {str(path)!r} (allowed: a run directory with {CHECKPOINT})")
    raw = path.read_bytes()
    try:
        record = msgpack.unpackb(raw, raw=False)
        meta_bytes, state_bytes, digest = record["meta"], record["state"], record["sha256"]
        host = record.get("host")
    except Exception:  # noqa: BLE001 - any decoding failure means the same thing
        raise CheckpointError(
            f"corrupted or truncated checkpoint {str(path)!r} ({len(raw)} bytes): not a checkpoint record"
        ) from None
    if not all(isinstance(b, bytes) for b in (meta_bytes, state_bytes, host or b"")):
        raise CheckpointError(f"corrupted checkpoint {str(path)!r}: malformed record")
    if hashlib.sha256(meta_bytes + state_bytes + (host or b"")).hexdigest() != digest:
        raise CheckpointError(f"corrupted checkpoint {str(path)!r}: sha256 mismatch")
    meta = json.loads(meta_bytes)
    if meta.get("format") != FORMAT:
        raise CheckpointError(
            f"checkpoint {str(path)!r} has format {meta.get('format')!r} (allowed: {FORMAT})"
        )
    if meta["fingerprint"] not in (config_fingerprint(cfg), config_fingerprint(cfg, _LEGACY_RESUMABLE_KEYS)):
        raise CheckpointError(
            f"checkpoint {str(path)!r} belongs to another run (or to a version of coherent_jax "
            f"with other config fields): its config fingerprint {meta['fingerprint'][:12]} "
            f"differs from this config's {config_fingerprint(cfg)[:12]}"
        )
    loop = dict(meta["loop"])
    loop["last_return"] = _from_json(loop["last_return"])
    loop["last_eval"] = {k: _from_json(v) for k, v in loop["last_eval"].items()}
    return Checkpoint(
        iteration=meta["iteration"],
        env_steps=meta["env_steps"],
        fingerprint=meta["fingerprint"],
        loop=LoopState(**loop),
        state_bytes=state_bytes,
        host=host,
    )


def split_resume(argv: list[str]) -> tuple[str | None, list[str]]:
    """The ``resume=`` value (the last one; None if absent or empty) and the other arguments."""
    resume_args = [a for a in argv if a.split("=", 1)[0].strip() == "resume"]
    rest = [a for a in argv if a not in resume_args]
    value = resume_args[-1].split("=", 1)[1].strip() if resume_args and "=" in resume_args[-1] else ""
    return value or None, rest


def resume_config(resume_dir: str, overrides: list[str]) -> tuple[Config, Path]:
    """The stored config of the run (or sweep) in `resume_dir` with `overrides` applied.

    Only `RESUMABLE_KEYS` may change; any other override is refused naming the key.
    The directory's recorded ``run_dir`` is not compared: a run resumes from wherever
    it now lives (moved, copied, or reached by another relative path). A ``run_dir``
    given with the resume must name the same directory.
    """
    path = Path(resume_dir)
    if not resume_dir or not path.is_dir():
        raise ConfigError(
            f"invalid value for 'resume': {resume_dir!r} (allowed: an existing run directory with {CONFIG})"
        )
    stored = load_config(path)
    given_dir = [o.split("=", 1)[1].strip() for o in overrides if o.split("=", 1)[0].strip() == "run_dir"]
    cfg = parse_overrides([o for o in overrides if o.split("=", 1)[0].strip() != "run_dir"], base=stored)
    changed = config_difference(cfg, stored)
    if changed is not None:
        raise ConfigError(
            f"invalid value for {changed!r} with resume: {getattr(cfg, changed)!r} "
            f"(allowed: the run's own value {getattr(stored, changed)!r})"
        )
    if given_dir and given_dir[-1] and Path(given_dir[-1]).resolve() != path.resolve():
        raise ConfigError(
            f"invalid value for 'run_dir' with resume: {given_dir[-1]!r} (allowed: {resume_dir!r})"
        )
    return dataclasses.replace(cfg, run_dir=str(path), resume=str(path)), path


def resume_point(run_dir: Path, cfg: Config, metrics: Path | None = None) -> Checkpoint | None:
    """The checkpoint a resume starts from, or None to start the run over from iteration 0.

    A run stopped before its first checkpoint (killed during the compile, say) has
    none; it starts over if it logged fewer rows than one checkpoint interval, and so
    does a run started with ``checkpoint_every=0`` (checkpoints only at the end and on
    SIGINT/SIGTERM) that was killed otherwise. Else a missing checkpoint is an error: it
    was lost, and starting over would overwrite logged work. A budget below the
    checkpoint's iteration is refused. `metrics` is the ``metrics.jsonl`` that tells how
    far it got (default: the run's own).
    """
    path = run_dir / CHECKPOINT
    if not path.exists():
        logged = len(read_metrics(metrics or run_dir / METRICS))
        only_at_end = load_config(run_dir).checkpoint_every == 0  # as the run was started
        if logged == 0 or only_at_end or (cfg.checkpoint_every > 0 and logged < cfg.checkpoint_every):
            return None
        raise CheckpointError(
            f"no checkpoint at {str(path)!r} although {logged} iterations were logged "
            f"(allowed: a run directory with {CHECKPOINT})"
        )
    ckpt = decode_checkpoint(path, cfg)
    if ckpt.iteration > cfg.num_iterations:
        raise ConfigError(
            f"invalid value for 'total_steps' with resume: {cfg.total_steps} "
            f"(allowed: at least the {ckpt.env_steps} env steps already done)"
        )
    return ckpt

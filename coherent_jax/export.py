"""Export a run's policy: ``python -m coherent_jax.export RUN_DIR format=onnx``.

``format=onnx`` writes ``RUN_DIR/policy.onnx`` (or ``out=PATH``): the deterministic action
with the observation normalisation and the task's action map, ``obs`` [N, o] -> ``action``
[N, p] float32, for any ONNX runtime (no JAX, no coherent_jax; the ``export`` extra,
``pip install -e ".[export]"``, provides ``onnx`` to write it). ``format=stablehlo`` writes
``RUN_DIR/policy.stablehlo``: the same function through ``jax.export`` with a symbolic
batch size, serialized (``jax.export.deserialize(blob).call(obs)``, JAX alone).
``format=hub`` writes the folder ``RUN_DIR/hub`` (or ``out=DIR``) to upload with the
Hub's own command-line tool: model card, config, parameters, the ONNX file and an
evaluation video where the task renders (`coherent_jax.policy.hub`; where it does not, one
line says why); nothing touches the network. The folder is written whole or not at all. An
existing output is refused unless ``force=true``. See docs/deploy.md.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from coherent_jax.config import ConfigError, cli
from coherent_jax.config.schema import MAX_SEED, SEED_ALLOWED
from coherent_jax.exit_codes import EXIT_BAD_INPUT
from coherent_jax.run import rundir
from coherent_jax.run.checkpoint import CHECKPOINT, PARAMS, CheckpointError, load_config

FORMATS = ("onnx", "stablehlo", "hub")
DEFAULT_NAMES = {"onnx": "policy.onnx", "stablehlo": "policy.stablehlo", "hub": "hub"}
EXPORT_EXTRA = 'pip install -e ".[export]"'

KEYS: dict[str, cli.Key] = {
    "format": cli.Key("onnx", cli.choice(FORMATS), " or ".join(FORMATS), "what to write"),
    "out": cli.Key(
        "", str, "a path", "where it goes; default RUN_DIR/policy.onnx, RUN_DIR/policy.stablehlo, RUN_DIR/hub"
    ),
    "force": cli.Key(False, cli.boolean, "true or false", "replace an existing output"),
    "episodes": cli.Key(10, cli.int_at_least(1), "an integer >= 1", "format=hub: evaluation episodes"),
    "seed": cli.Key(0, cli.int_between(0, MAX_SEED), SEED_ALLOWED, "format=hub: evaluation seed"),
}
_SETTING = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
USAGE = "usage: python -m coherent_jax.export RUN_DIR [format=onnx|stablehlo|hub] [out=PATH] [force=true]"


def parse_export_args(argv: Sequence[str]) -> tuple[Path, dict]:
    """``RUN_DIR`` then ``key=value`` settings; raises `ConfigError` in one line."""
    is_setting = [bool(_SETTING.match(a)) and not os.path.isdir(a) for a in argv]
    positional = [a for a, s in zip(argv, is_setting, strict=True) if not s]
    if len(positional) != 1:
        raise ConfigError(f"expected one run directory, got {len(positional)}: {positional!r} ({USAGE})")
    items = [a for a, s in zip(argv, is_setting, strict=True) if s]
    settings = cli.parse_command(items, KEYS, command="export", config=False).settings
    return Path(positional[0]), settings


def check_input(run_dir: Path, opts: dict) -> Path:
    """The output path, after every check that needs no JAX; raises `ConfigError` in one line."""
    rundir.check_one_run(run_dir, "export")
    load_config(run_dir)
    if not (run_dir / CHECKPOINT).is_file() and not (run_dir / PARAMS).is_file():
        raise ConfigError(
            f"invalid run directory {str(run_dir)!r}: no {CHECKPOINT} or {PARAMS} (allowed: a trained run)"
        )
    out = Path(opts["out"]) if opts["out"] else run_dir / DEFAULT_NAMES[opts["format"]]
    if out.exists() and not opts["force"]:
        raise ConfigError(
            f"invalid value for 'out': {str(out)!r} exists (allowed: a new path, or force=true)"
        )
    if out.exists() and opts["format"] == "hub" and not (out / "policy.json").is_file():
        raise ConfigError(
            f"invalid value for 'out': {str(out)!r} exists and is not a Hub folder of this command "
            "(allowed: a new path, or an earlier format=hub folder with force=true)"
        )
    if opts["format"] != "stablehlo":
        try:
            import onnx  # noqa: F401  # lazy: optional dependency (export extra), checked before writing
        except ImportError:
            raise ConfigError(
                f"format={opts['format']} needs onnx: install the export extra, {EXPORT_EXTRA}"
            ) from None
    return out


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(f"{USAGE}\n\noptions (key=default):")
        print("\n".join(cli.help_lines(KEYS)))
        return 0
    os.environ.setdefault("MUJOCO_GL", "egl")  # the Hub folder's video; before mujoco is imported
    try:
        run_dir, opts = parse_export_args(argv)
        out = check_input(run_dir, opts)
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    from coherent_jax.policy import formats, hub, load_policy  # lazy: JAX, after the input is checked

    try:
        if opts["format"] == "hub":
            figures = hub.write_hub(run_dir, out, opts["episodes"], opts["seed"], replace=opts["force"])
            if figures["replay_skipped"]:
                print(f"[coherent_jax] no replay video: {figures['replay_skipped']}", flush=True)
            print(
                f"[coherent_jax] Hub folder {out}: return {figures['return_mean']:.2f} +- "
                f"{figures['return_std']:.2f} over {opts['episodes']} episodes",
                flush=True,
            )
            return 0
        policy = load_policy(run_dir)
        write = formats.write_onnx if opts["format"] == "onnx" else formats.write_stablehlo
        out.parent.mkdir(parents=True, exist_ok=True)
        write(policy, out)
    except (CheckpointError, ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"[coherent_jax] {policy!r} -> {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Command-line training: ``python -m coherent_jax.train env=halfcheetah algo=ppo ...``.

Overrides are ``key=value`` (``--help`` lists them all). A bad override is
reported in one line and exits with status 2 before anything is written. A run
writes one directory: ``config.yaml`` (resolved config), ``metrics.jsonl`` (one
row per iteration, with ``eval/*`` on evaluation rows), ``params.msgpack`` (final
parameters and observation statistics, flax serialisation) and ``summary.json``.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import Config, ConfigError, help_text, parse_overrides, to_dict


def default_run_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.env}-{cfg.algo}-{cfg.explore}-s{cfg.seed}-{stamp}"


def prepare_run_dir(cfg: Config) -> Path:
    """Creates the run directory; refuses one that already holds files."""
    path = Path(cfg.run_dir) if cfg.run_dir else default_run_dir(cfg)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise ConfigError(f"invalid value for 'run_dir': {str(path)!r} (allowed: a new or empty directory)")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _to_float(x: Any) -> float | None:
    value = float(x)
    return value if math.isfinite(value) else None


def run_keys(seed: int):
    """(key, init_key) of a run: ``init_key`` starts the state, ``key`` is split once per evaluation.

    Sweeps derive each grid point's keys with this same function, so a point equals
    the single run with its settings.
    """
    import jax

    key = jax.random.PRNGKey(seed)
    key, init_key = jax.random.split(key)
    return key, init_key


def train(
    cfg: Config,
    run_dir: Path | None = None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
) -> dict[str, Any]:
    """Runs training for ``cfg``; returns the summary (also written to ``run_dir``).

    ``progress_fn(iteration, metrics)`` receives every iteration's metrics (as
    Python floats), in the manner of Brax's trainers.
    """
    import jax
    from flax import serialization
    from tqdm.auto import tqdm

    from coherent_jax import parallel
    from coherent_jax.agents import make_trainer

    t_start = time.perf_counter()
    num_devices = parallel.resolve_num_devices(cfg.num_devices)
    parallel.check_env_split(cfg.num_envs, num_devices)
    trainer = make_trainer(cfg)
    key, init_key = run_keys(cfg.seed)
    state, shardings = parallel.init_state(trainer, init_key, num_devices, cfg.num_envs)

    t0 = time.perf_counter()
    iteration = parallel.compile_iteration(trainer, state, shardings)
    evaluate = jax.jit(trainer.evaluate).lower(state, key).compile()
    compile_s = time.perf_counter() - t0
    print(
        f"[coherent_jax] {cfg.env} {cfg.algo} explore={cfg.explore}: compiled in {compile_s:.1f} s; "
        f"{cfg.num_iterations} iterations of {cfg.steps_per_iteration} env steps"
        + (f" on {num_devices} devices" if num_devices > 1 else ""),
        flush=True,
    )

    metrics_file = open(run_dir / "metrics.jsonl", "w") if run_dir else None
    bar = tqdm(
        total=cfg.num_iterations * cfg.steps_per_iteration,
        unit="step",
        disable=not cfg.progress,
        dynamic_ncols=True,
        mininterval=1.0,
    )
    train_s = eval_s = 0.0
    last_eval: dict[str, float] = {}
    last_return = float("nan")
    try:
        for i in range(cfg.num_iterations):
            t0 = time.perf_counter()
            state, metrics = iteration(state)
            metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
            train_s += time.perf_counter() - t0
            last = i == cfg.num_iterations - 1
            if last or (cfg.eval_every > 0 and (i + 1) % cfg.eval_every == 0):
                t0 = time.perf_counter()
                key, eval_key = jax.random.split(key)
                last_eval = {k: float(v) for k, v in jax.device_get(evaluate(state, eval_key)).items()}
                eval_s += time.perf_counter() - t0
                metrics.update(last_eval)
            if not math.isnan(metrics["train/episode_return"]):
                last_return = metrics["train/episode_return"]
            env_steps = (i + 1) * cfg.steps_per_iteration
            row = {"iteration": i + 1, "env_steps": env_steps, "time_s": time.perf_counter() - t_start}
            row.update({k: _to_float(v) for k, v in metrics.items()})
            if metrics_file:
                metrics_file.write(json.dumps(row) + "\n")
                metrics_file.flush()
            if progress_fn:
                progress_fn(i + 1, metrics)
            bar.update(cfg.steps_per_iteration)
            bar.set_postfix(
                sps=f"{env_steps / max(train_s, 1e-9):.0f}",
                ret=f"{last_return:.1f}",
                eval=f"{last_eval.get('eval/episode_return', float('nan')):.1f}",
                refresh=False,
            )
    finally:
        bar.close()
        if metrics_file:
            metrics_file.close()

    total_steps = cfg.num_iterations * cfg.steps_per_iteration
    summary = {
        "env": cfg.env,
        "algo": cfg.algo,
        "explore": cfg.explore,
        "seed": cfg.seed,
        "env_steps": total_steps,
        "final_eval_return": last_eval.get("eval/episode_return"),
        "final_eval_return_std": last_eval.get("eval/episode_return_std"),
        "final_train_return": _to_float(last_return),
        "compile_s": round(compile_s, 2),
        "train_s": round(train_s, 2),
        "eval_s": round(eval_s, 2),
        "wall_s": round(time.perf_counter() - t_start, 2),
        "train_env_steps_per_s": round(total_steps / max(train_s, 1e-9), 1),
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "num_devices": num_devices,
    }
    if run_dir:
        payload = trainer.export_params(state)
        _atomic_write(run_dir / "params.msgpack", serialization.to_bytes(jax.device_get(payload)))
        _atomic_write(run_dir / "summary.json", json.dumps(summary, indent=2).encode())
    print(
        f"[coherent_jax] done: eval return {summary['final_eval_return']:.1f}, "
        f"{summary['train_env_steps_per_s']:.0f} env steps/s training, compile {compile_s:.1f} s, "
        f"wall {summary['wall_s']:.0f} s" + (f"; run dir {run_dir}" if run_dir else ""),
        flush=True,
    )
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(help_text())
        return 0
    try:
        cfg = parse_overrides(argv)
        writer = check_devices(cfg)
        run_dir = prepare_run_dir(cfg) if writer else None
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from omegaconf import OmegaConf

    if run_dir:
        _atomic_write(run_dir / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())
        print(f"[coherent_jax] run dir {run_dir}", flush=True)
    train(cfg, run_dir)
    return 0


def check_devices(cfg: Config, split_envs: bool = True) -> bool:
    """Initialises multi-host JAX if asked and checks the device split before anything is written.

    Returns whether this process writes the outputs (process 0 of a distributed run).
    """
    from coherent_jax import parallel

    parallel.maybe_initialize_distributed(cfg.distributed)
    num_devices = parallel.resolve_num_devices(cfg.num_devices)
    if split_envs:
        parallel.check_env_split(cfg.num_envs, num_devices)
    import jax

    return jax.process_index() == 0


if __name__ == "__main__":
    sys.exit(main())

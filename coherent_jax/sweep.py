"""Sweeps in one program: ``python -m coherent_jax.sweep explore=coherent seeds=8 beta=[0,0.01,0.1,1]``.

Every ``key=value`` of `python -m coherent_jax.train` is accepted; a key of
`config.SWEEPABLE` (or ``seed``) given a list, ``beta=[0,0.01,0.1,1]``, becomes an
axis of the grid, and ``seeds=N`` runs each point with seeds ``seed, seed+1, ...,
seed+N-1``. The grid is the product of the axes (seeds innermost). Only the
hyperparameters that live in the train state as arrays (``state.hparams``) can
vary, so the whole grid is one program:

    states = vmap(trainer.init)(init_keys, hparams)       # one row per grid point
    states, metrics = vmap(trainer.iteration)(states)     # compiled once, looped in Python

Each point derives its keys exactly as a single run does (`train.run_keys`), so
point i equals ``python -m coherent_jax.train`` with that point's settings (same
metrics up to the order of float sums that vmap may change). With several JAX
devices the points are split over them (`parallel.point_shardings`).

Outputs, in ``run_dir`` (default ``runs/sweep-<env>-<algo>-<explore>-<time>``): one
directory per point named by its settings, holding what a single run writes
(``config.yaml``, ``metrics.jsonl``, ``params.msgpack``, ``summary.json``), and the
aggregate over seeds of the final evaluation return per non-seed point,
``sweep.csv`` and ``sweep.json``, also printed. A bad key or value (an unknown
key, a list for a shape setting, an empty list, a value out of range) is one
line on stderr and exit status 2 before anything is written.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import json
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax import distributed
from coherent_jax.config import SWEEPABLE, Config, ConfigError, help_text, parse_overrides, to_dict
from coherent_jax.runs import atomic_write
from coherent_jax.train import _to_float, check_devices, prepare_run_dir, run_keys

# Keys that may take a list of values: the state's array hyperparameters, and seed.
AXIS_KEYS = (*SWEEPABLE, "seed")


@dataclasses.dataclass(frozen=True)
class Point:
    """One grid point: its settings along the non-seed axes, its seed and its config."""

    index: int
    values: dict[str, Any]
    seed: int
    cfg: Config

    @property
    def name(self) -> str:
        parts = [f"{k}={_fmt(v)}" for k, v in self.values.items()]
        return "-".join([f"p{self.index:03d}", *parts, f"seed={self.seed}"])


@dataclasses.dataclass(frozen=True)
class SweepPlan:
    """The validated grid: the shared config, the axes in the order given, the seeds, the points."""

    base: Config
    axes: dict[str, list[Any]]
    seeds: list[int]
    points: list[Point]


def _fmt(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _is_list(text: str) -> bool:
    return text.startswith("[") and text.endswith("]")


def _list_items(key: str, text: str) -> list[str]:
    items = [s.strip() for s in text[1:-1].split(",")]
    if items == [""] or any(not s for s in items):
        raise ConfigError(
            f"invalid value for {key!r}: {text!r} (allowed: a non-empty list of values, e.g. [0.01,0.1])"
        )
    return items


def parse_sweep(argv: Sequence[str]) -> SweepPlan:
    """Splits ``key=value`` strings into the grid; raises `ConfigError` naming the bad key or value."""
    fields = {f.name: f for f in dataclasses.fields(Config)}
    scalars: list[str] = []
    axes: dict[str, list[str]] = {}
    num_seeds = None
    for item in argv:
        if "=" not in item or item.startswith("="):
            raise ConfigError(f"malformed override {item!r}: expected key=value")
        key, text = (s.strip() for s in item.split("=", 1))
        if key == "seeds":
            try:
                num_seeds = int(text)
            except ValueError:
                num_seeds = 0
            if num_seeds < 1:
                raise ConfigError(f"invalid value for 'seeds': {text!r} (allowed: an integer >= 1)")
        elif key in fields and _is_list(text):
            list_field = "list" in str(fields[key].type)
            if list_field and not text.startswith("[["):
                scalars.append(item)  # e.g. policy_hidden=[64,64]: one value of a list setting
                continue
            if key not in AXIS_KEYS:
                raise ConfigError(
                    f"invalid value for {key!r}: {text!r} (allowed: one value; it sets shapes or the "
                    f"program, so it cannot vary within a sweep; keys that take a list: "
                    f"{', '.join(AXIS_KEYS)})"
                )
            axes[key] = _list_items(key, text)
        else:
            scalars.append(item)
    base = parse_overrides(scalars)  # unknown keys and bad single values end here
    seed_items = axes.pop("seed", None)
    if seed_items is not None and num_seeds is not None:
        raise ConfigError(
            f"invalid key 'seeds': {num_seeds} with seed={seed_items} "
            "(allowed: either seeds=N or a list of seeds)"
        )
    if seed_items is None:
        seed_items = [str(base.seed + i) for i in range(num_seeds or 1)]

    points: list[Point] = []
    typed_axes: dict[str, list[Any]] = {k: [] for k in axes}
    seeds: list[int] = []
    for combo in itertools.product(*axes.values(), seed_items):
        *values, seed_text = combo
        overrides = [f"{k}={v}" for k, v in zip(axes, values, strict=True)] + [f"seed={seed_text}"]
        cfg = parse_overrides([*scalars, *overrides])  # validates each value, e.g. beta=2
        typed = {k: getattr(cfg, k) for k in axes}
        for k, v in typed.items():
            if v not in typed_axes[k]:
                typed_axes[k].append(v)
        if cfg.seed not in seeds:
            seeds.append(cfg.seed)
        points.append(Point(index=len(points), values=typed, seed=cfg.seed, cfg=cfg))
    return SweepPlan(base=base, axes=typed_axes, seeds=seeds, points=points)


def default_sweep_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"sweep-{cfg.env}-{cfg.algo}-{cfg.explore}-{stamp}"


def build_hparams(plan: SweepPlan, env, eval_env) -> list[Any]:
    """Each point's ``init_hparams()``, from a trainer built for that point's config.

    Raises `ConfigError` if an axis does not reach the state's hyperparameters for
    this algorithm (e.g. ``clip_eps`` for SAC): such a sweep would run identical points.
    """
    import jax
    import numpy as np

    from coherent_jax.agents import make_trainer

    hparams = [make_trainer(p.cfg, env, eval_env).init_hparams() for p in plan.points]
    structure = jax.tree.structure(hparams[0])
    leaves = [[np.asarray(x) for x in jax.tree.leaves(h)] for h in hparams]
    for h in hparams[1:]:
        if jax.tree.structure(h) != structure:  # would mean a swept key changed the program
            raise ConfigError("invalid sweep: the grid points' hyperparameters differ in structure")
    for key, values in plan.axes.items():
        if len(values) < 2:
            continue
        first = plan.points[0]
        other = next(
            p
            for p in plan.points
            if p.seed == first.seed
            and p.values[key] == values[1]
            and all(p.values[k] == first.values[k] for k in plan.axes if k != key)
        )
        same = all(
            np.array_equal(a, b) for a, b in zip(leaves[first.index], leaves[other.index], strict=True)
        )
        if same:
            raise ConfigError(
                f"invalid key {key!r}: algo={plan.base.algo} explore={plan.base.explore} does not use it "
                f"(allowed: keys that change its hyperparameters)"
            )
    return hparams


def point_device_count(num_points: int, available: int) -> int:
    """The largest device count up to `available` that divides the points (each device runs whole points)."""
    return max(d for d in range(1, available + 1) if num_points % d == 0)


def run_sweep(plan: SweepPlan, out_dir: Path | None, env=None, eval_env=None) -> dict[str, Any]:
    """Runs every point of ``plan`` as one vmapped program; writes and returns the aggregate.

    ``env`` and ``eval_env`` (`VecEnv`s of the plan's shapes) are built if not given.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np
    from flax import serialization
    from tqdm.auto import tqdm

    from coherent_jax import parallel
    from coherent_jax.agents import make_trainer
    from coherent_jax.envs.vec_env import VecEnv

    cfg = plan.base
    t_start = time.perf_counter()
    env = env or VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    eval_env = eval_env or VecEnv(
        cfg.env, cfg.eval_episodes, cfg.episode_length, cfg.physics, cfg.physics_threads
    )
    hparams = build_hparams(plan, env, eval_env)
    trainer = make_trainer(cfg, env, eval_env)  # shapes and program: shared by every point
    num_points = len(plan.points)
    stacked_hp = jax.tree.map(lambda *xs: jnp.stack(xs), *hparams)
    keys = [run_keys(p.seed) for p in plan.points]
    key = jnp.stack([k for k, _ in keys])
    init_keys = jnp.stack([k for _, k in keys])

    # The largest device count that divides the points (each device runs whole points).
    num_devices = point_device_count(num_points, parallel.resolve_num_devices(cfg.num_devices))
    init = jax.vmap(trainer.init)
    step = jax.vmap(trainer.iteration)
    t0 = time.perf_counter()
    if num_devices == 1:
        states = jax.jit(init)(init_keys, stacked_hp)
        iteration = jax.jit(step, donate_argnums=0).lower(states).compile()
    else:
        mesh = parallel.make_mesh(num_devices, parallel.POINT_AXIS)
        shardings = parallel.point_shardings(jax.eval_shape(init, init_keys, stacked_hp), mesh)
        states = jax.jit(init, out_shardings=shardings)(init_keys, stacked_hp)
        metric_sharding = parallel.NamedSharding(mesh, parallel.PartitionSpec(parallel.POINT_AXIS))
        iteration = (
            jax.jit(
                step, in_shardings=(shardings,), out_shardings=(shardings, metric_sharding), donate_argnums=0
            )
            .lower(states)
            .compile()
        )
    evaluate = jax.jit(jax.vmap(trainer.evaluate)).lower(states, key).compile()
    compile_s = time.perf_counter() - t0
    devices_note = f" over {num_devices} devices" if num_devices > 1 else ""
    print(
        f"[coherent_jax] sweep of {num_points} points ({cfg.env} {cfg.algo} explore={cfg.explore}): "
        f"compiled in {compile_s:.1f} s; {cfg.num_iterations} iterations of {cfg.steps_per_iteration} "
        f"env steps per point{devices_note}",
        flush=True,
    )

    point_dirs: list[Path] = []
    files = []
    if out_dir is not None:
        from omegaconf import OmegaConf

        for p in plan.points:
            d = out_dir / p.name
            d.mkdir()
            # The point's own settings, as the single run that it equals would record them.
            point_cfg = dataclasses.replace(p.cfg, run_dir=str(d))
            atomic_write(d / "config.yaml", OmegaConf.to_yaml(to_dict(point_cfg)).encode())
            point_dirs.append(d)
            files.append(open(d / "metrics.jsonl", "w"))
    bar = tqdm(
        total=cfg.num_iterations,
        unit="it",
        disable=not cfg.progress or not distributed.is_writer(),  # one progress bar per run
        dynamic_ncols=True,
        mininterval=1.0,
    )
    train_s = eval_s = 0.0
    last_eval: dict[str, np.ndarray] = {}
    last_return = np.full((num_points,), np.nan)
    try:
        for i in range(cfg.num_iterations):
            t0 = time.perf_counter()
            states, metrics = iteration(states)
            metrics = {k: np.asarray(v, np.float64) for k, v in distributed.to_host(metrics).items()}
            train_s += time.perf_counter() - t0
            if i == cfg.num_iterations - 1 or (cfg.eval_every > 0 and (i + 1) % cfg.eval_every == 0):
                t0 = time.perf_counter()
                split = jax.vmap(jax.random.split)(key)  # each point: key, eval_key = split(key)
                key, eval_key = split[:, 0], split[:, 1]
                evaluated = distributed.to_host(evaluate(states, eval_key))
                last_eval = {k: np.asarray(v, np.float64) for k, v in evaluated.items()}
                eval_s += time.perf_counter() - t0
                metrics.update(last_eval)
            ret = metrics["train/episode_return"]
            last_return = np.where(np.isnan(ret), last_return, ret)
            env_steps = (i + 1) * cfg.steps_per_iteration
            for j, f in enumerate(files):
                row = {"iteration": i + 1, "env_steps": env_steps, "time_s": time.perf_counter() - t_start}
                row.update({k: _to_float(v[j]) for k, v in metrics.items()})
                f.write(json.dumps(row) + "\n")
                f.flush()
            bar.update(1)
            bar.set_postfix(
                sps=f"{num_points * env_steps / max(train_s, 1e-9):.0f}",
                ret=f"{np.nanmean(last_return):.1f}" if np.isfinite(last_return).any() else "nan",
                refresh=False,
            )
    finally:
        bar.close()
        for f in files:
            f.close()

    total_steps = cfg.num_iterations * cfg.steps_per_iteration
    common = {
        "env_steps": total_steps,
        "compile_s": round(compile_s, 2),
        "train_s": round(train_s, 2),
        "eval_s": round(eval_s, 2),
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "num_devices": num_devices,
    }
    summaries = []
    for j, p in enumerate(plan.points):
        summaries.append(
            {
                "point": p.index,
                "name": p.name,
                **{k: v for k, v in p.values.items()},
                "seed": p.seed,
                "env": cfg.env,
                "algo": cfg.algo,
                "explore": cfg.explore,
                "final_eval_return": _to_float(last_eval["eval/episode_return"][j]),
                "final_eval_return_std": _to_float(last_eval["eval/episode_return_std"][j]),
                "final_train_return": _to_float(last_return[j]),
                **common,
            }
        )
    rows = aggregate(plan, summaries)
    result = {
        "axes": plan.axes,
        "seeds": plan.seeds,
        "num_points": num_points,
        **common,
        "wall_s": round(time.perf_counter() - t_start, 2),
        "sweep_env_steps_per_s": round(num_points * total_steps / max(train_s, 1e-9), 1),
        "rows": rows,
        "points": summaries,
    }
    params = distributed.to_host(trainer.export_params(states))  # every process: a collective
    if out_dir is not None:
        for j, d in enumerate(point_dirs):
            one = jax.tree.map(lambda x, j=j: x[j], params)
            atomic_write(d / "params.msgpack", serialization.to_bytes(one))
            atomic_write(d / "summary.json", json.dumps(summaries[j], indent=2).encode())
        atomic_write(out_dir / "sweep.csv", to_csv(plan, rows).encode())
        atomic_write(out_dir / "sweep.json", json.dumps(result, indent=2).encode())
    print(format_table(plan, rows), flush=True)
    print(
        f"[coherent_jax] sweep done: {result['sweep_env_steps_per_s']:.0f} env steps/s over all points, "
        f"compile {compile_s:.1f} s, wall {result['wall_s']:.0f} s"
        + (f"; results in {out_dir}" if out_dir else ""),
        flush=True,
    )
    return result


def aggregate(plan: SweepPlan, summaries: list[dict]) -> list[dict]:
    """Mean and (population) std over seeds of the final eval return, per non-seed point."""
    groups: dict[tuple, list[dict]] = {}
    for s in summaries:
        groups.setdefault(tuple(s[k] for k in plan.axes), []).append(s)
    rows = []
    for values, members in groups.items():
        returns = [m["final_eval_return"] for m in members if m["final_eval_return"] is not None]
        rows.append(
            {
                **dict(zip(plan.axes, values, strict=True)),
                "seeds": len(members),
                "final_eval_return_mean": statistics.fmean(returns) if returns else None,
                "final_eval_return_std": statistics.pstdev(returns) if returns else None,
                "non_finite": len(members) - len(returns),
            }
        )
    return rows


def to_csv(plan: SweepPlan, rows: list[dict]) -> str:
    buf = io.StringIO()
    columns = [*plan.axes, "seeds", "final_eval_return_mean", "final_eval_return_std", "non_finite"]
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def format_table(plan: SweepPlan, rows: list[dict]) -> str:
    header = (
        "".join(f"{k:>12}" for k in plan.axes) + f"{'seeds':>7}  final eval return (mean ± std over seeds)"
    )
    lines = [header]
    for r in rows:
        mean, std = r["final_eval_return_mean"], r["final_eval_return_std"]
        value = "non-finite" if mean is None else f"{mean:10.1f} ± {std:.1f}"
        lines.append("".join(f"{_fmt(r[k]):>12}" for k in plan.axes) + f"{r['seeds']:>7}  {value}")
    return "\n".join(lines)


def sweep_help() -> str:
    return "\n".join(
        [
            "usage: python -m coherent_jax.sweep [key=value ...] [seeds=N] [KEY=[v1,v2,...] ...]",
            f"keys that take a list of values (the grid's axes): {', '.join(AXIS_KEYS)}",
            "seeds=N: seeds seed, seed+1, ..., seed+N-1 for every point (default 1)",
            "run_dir: the sweep's directory (one sub-directory per point, plus sweep.csv and sweep.json)",
            "",
            help_text().split("\n", 1)[1],
        ]
    )


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(sweep_help())
        return 0
    try:
        plan = parse_sweep(argv)
        if distributed.needs_supervisor(plan.base.distributed):
            return distributed.supervise("coherent_jax.sweep", argv)
        writer = check_devices(plan.base, split_envs=False)
        from coherent_jax import parallel

        available = parallel.resolve_num_devices(plan.base.num_devices)
        distributed.check_device_split(point_device_count(len(plan.points), available))
        from coherent_jax.envs.vec_env import VecEnv

        cfg = plan.base
        env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
        eval_env = VecEnv(cfg.env, cfg.eval_episodes, cfg.episode_length, cfg.physics, cfg.physics_threads)
        build_hparams(plan, env, eval_env)  # refuses an axis without effect, before anything is written
        out_dir = None
        if writer:
            out_dir = prepare_run_dir(
                dataclasses.replace(cfg, run_dir=cfg.run_dir or str(default_sweep_dir(cfg)))
            )
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if out_dir is not None:
        print(f"[coherent_jax] sweep dir {out_dir}: {len(plan.points)} points", flush=True)
    run_sweep(plan, out_dir, env, eval_env)
    return 0


if __name__ == "__main__":
    sys.exit(distributed.run_cli(main))

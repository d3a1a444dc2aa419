"""The ``throughput`` suite, the default: ``python -m benchmarks [throughput] [key=value ...]``.

In one process on one task and one set of settings: the raw vectorized env rate
(random actions), the training rate of PPO, Coherent-PPO, SAC and Coherent-SAC,
and Brax's own PPO trainer on the same env and batch layout, with compile times
apart, peak memory and the ratios. Settings are ``key=value``: every training key
except ``algo`` and ``explore`` (the rows set those), plus `KEYS`. The results go
to a JSON file (default ``bench_results/throughput.json``), written atomically.
"""

from __future__ import annotations

import dataclasses
import functools
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
from flax import linen

from benchmarks import IGNORED, measure
from coherent_jax.agents import make_trainer
from coherent_jax.config import Config, cli, parse_overrides, to_dict
from coherent_jax.envs.brax_env import make_brax_env
from coherent_jax.envs.registry import brax_counterpart
from coherent_jax.envs.vec_env import VecEnv

# Rows besides the raw env; brax_ppo is Brax's own trainer.
ROWS = ("ppo", "coherent_ppo", "sac", "coherent_sac", "brax_ppo")
# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "over 15 min (stopped at 900 s in round 2 of 9, the last with its ~75 s SAC rows)"
KEYS: dict[str, cli.Key] = {
    "iterations": cli.Key(
        9, cli.int_at_least(1), "an integer >= 1", "timed iterations per row (after one warm-up)"
    ),
    "out": cli.Key(
        "bench_results/throughput.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
    "sac_iterations": cli.Key(
        2,
        cli.int_at_least(1),
        "an integer >= 1",
        "timed iterations of the SAC rows (UTD 1: num_envs * unroll_length updates each, slow on CPU), "
        "in the first rounds",
    ),
    "rows": cli.Key(
        list(ROWS),
        cli.choice_list(ROWS),
        "a non-empty list of " + ", ".join(ROWS),
        "rows besides the raw env",
    ),
}
# Training keys the suite sets itself: every row has its own algorithm and strategy.
FIXED: dict[str, str | None] = {"algo": None, "explore": None}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings and training config; `ConfigError` in one line for bad input.

    Every row's config is built here too, so that a setting one row refuses (a
    ``coherent.*`` key SAC does not take) stops the suite before it compiles anything.
    """
    parsed = cli.parse_command(items, KEYS, command="the throughput suite", fixed=FIXED, ignored=IGNORED)
    _throughput_configs(parsed.config, parsed.config_items, parsed.settings["rows"])
    return parsed


def _throughput_configs(cfg: Config, items: list[str], rows: Sequence[str]) -> dict[str, Config]:
    """The trainer rows: our PPO and Coherent-PPO on ``cfg``; SAC rows on SAC's defaults.

    SAC keeps its own defaults (networks, batch, UTD ratio; `ALGO_DEFAULTS`) but the
    bench's task, env count, unroll and episode length, and its random-action warm-up
    is one iteration long, so that the timed iterations all do gradient updates.
    """
    configs = {}
    for name, explore in (("ppo", "action"), ("coherent_ppo", "coherent")):
        if name in rows:
            configs[name] = dataclasses.replace(cfg, algo="ppo", explore=explore)
    shared = [f"{k}={getattr(cfg, k)}" for k in ("env", "num_envs", "unroll_length", "episode_length")]
    for name, explore in (("sac", "action"), ("coherent_sac", "coherent")):
        if name in rows:
            configs[name] = parse_overrides(
                [
                    "algo=sac",
                    f"explore={explore}",
                    *items,
                    *shared,
                    f"sac.warmup_steps={cfg.steps_per_iteration}",
                ]
            )
    return configs


def _raw_rollout(env):
    """``(env_state, key) -> (env_state, key, reward sum)``: ``unroll_length`` random-action steps."""

    def rollout(env_state, key, length):
        def step(state, k):
            action = jax.random.uniform(k, (env.num_envs, env.action_size), minval=-1.0, maxval=1.0)
            state, outcome = env.step(state, action)
            return state, outcome.reward.sum()

        key, sub = jax.random.split(key)
        env_state, rewards = jax.lax.scan(step, env_state, jax.random.split(sub, length))
        return env_state, key, jnp.sum(rewards)

    return rollout


def _brax_ppo(cfg: Config, iterations: int, log, between_epochs: Callable[[int], None] | None = None) -> dict:
    """Brax's own PPO (`brax.training.agents.ppo.train`) on the same env and batch layout.

    One Brax training step is one of our iterations: ``batch_size * num_minibatches =
    num_envs`` makes it collect one unroll of ``unroll_length`` steps from every env,
    then ``num_updates_per_batch`` epochs of ``num_minibatches`` minibatches of whole
    env segments. One step per Brax epoch, ``iterations + 2`` epochs: Brax times each
    epoch itself (its ``training/sps``). The first two are warm-up: the first compiles,
    and Brax 0.14.2 recompiles its training epoch once, in the second, on CPU. The
    steady rate is the median of epochs 3 .. iterations + 2 (as many as our timed
    iterations); compile time is the time all epochs took above that median.

    ``between_epochs(i)`` runs after Brax's epoch ``i + 2`` (i = 0 .. iterations-1), once
    Brax is compiled and warm: the suite times one round of its own rows there, so
    that Brax's epochs and our iterations alternate under the same machine load.
    Brax's epoch time is its own ``training/walltime``, which excludes this callback.
    """
    from brax.training.agents.ppo import train as brax_train  # lazy: brax training, one row

    steps = cfg.steps_per_iteration
    epochs = iterations + 2
    network_factory, settings = _brax_settings(cfg, epochs)
    epoch_s: list[float] = []
    sps: list[float] = []
    walltime = [0.0]

    def progress(step, metrics):
        if "training/walltime" in metrics:
            epoch_s.append(float(metrics["training/walltime"]) - walltime[0])
            walltime[0] = float(metrics["training/walltime"])
            sps.append(float(metrics["training/sps"]))
            log(
                f"[bench]   brax ppo epoch {len(epoch_s)}/{epochs}: {epoch_s[-1]:.2f} s "
                f"({sps[-1]:,.0f} steps/s)"
            )
            if between_epochs is not None and 2 <= len(epoch_s) < epochs:
                between_epochs(len(epoch_s) - 2)

    log(f"[bench] brax ppo: {epochs} epochs of one training step ({steps} env steps), compiling in the first")
    # Brax's trainer runs Brax environments: a Gymnasium task is timed on its Brax re-creation.
    env = make_brax_env(brax_counterpart(cfg.env))
    t0 = time.perf_counter()
    brax_train.train(environment=env, network_factory=network_factory, progress_fn=progress, **settings)
    wall_s = time.perf_counter() - t0
    jax.clear_caches()
    return _brax_result(cfg, settings, epoch_s, sps, wall_s)


def _brax_settings(cfg: Config, epochs: int) -> tuple[Callable, dict[str, Any]]:
    """Brax PPO's network factory and ``train`` settings matching ``cfg`` (``epochs`` epochs of one step)."""
    from brax.training.agents.ppo import networks as brax_networks  # lazy: brax training, one row

    steps = cfg.steps_per_iteration
    activation = {"tanh": linen.tanh, "relu": linen.relu, "elu": linen.elu, "swish": linen.swish}
    network_factory = functools.partial(
        brax_networks.make_ppo_networks,
        policy_hidden_layer_sizes=tuple(cfg.policy_hidden),
        value_hidden_layer_sizes=tuple(cfg.value_hidden),
        activation=activation[cfg.activation],
        distribution_type="normal",  # a Gaussian with a state-independent learned log-std, like ours
        noise_std_type="log",
        init_noise_std=cfg.init_std,
    )
    settings = dict(
        num_timesteps=epochs * steps,
        episode_length=cfg.episode_length,
        num_envs=cfg.num_envs,
        unroll_length=cfg.unroll_length,
        batch_size=cfg.num_envs // cfg.ppo.num_minibatches,
        num_minibatches=cfg.ppo.num_minibatches,
        num_updates_per_batch=cfg.ppo.num_epochs,
        learning_rate=cfg.lr,
        entropy_cost=cfg.ppo.ent_coef,
        discounting=cfg.gamma,
        gae_lambda=cfg.ppo.gae_lambda,
        clipping_epsilon=cfg.ppo.clip_eps,
        max_grad_norm=cfg.ppo.max_grad_norm,
        normalize_observations=cfg.normalize_obs,
        normalize_advantage=cfg.ppo.normalize_advantages,
        vf_loss_coefficient=cfg.ppo.vf_coef,
        # Brax's own env wrappers set no info["time_out"], which bootstrap_on_timeout needs.
        bootstrap_on_timeout=False,
        num_evals=epochs + 1,
        run_evals=False,
        seed=cfg.seed,
    )
    return network_factory, settings


def _brax_result(
    cfg: Config, settings: dict[str, Any], epoch_s: list[float], sps: list[float], wall_s: float
) -> dict:
    """Brax PPO's row: the steady epochs' median (epochs 3 on), compile and setup apart, what differs."""
    steps = cfg.steps_per_iteration
    steady = epoch_s[2:]
    median = statistics.median(steady)
    return {
        "settings": {k: v for k, v in settings.items()},
        "network": {
            "policy_hidden": list(cfg.policy_hidden),
            "value_hidden": list(cfg.value_hidden),
            "activation": cfg.activation,
            "distribution": "normal, state-independent log std",
        },
        "epoch_s": epoch_s,
        "brax_reported_sps": sps,
        "iteration_s": steady,
        "iteration_s_median": median,
        "env_steps_per_s": steps / median,
        "env_steps_per_s_best": steps / min(steady),
        # Time above the steady epoch's: the first epoch's compile and the recompilation.
        "compile_s": sum(max(0.0, t - median) for t in epoch_s),
        "setup_s": wall_s - sum(epoch_s),  # env reset, network init and their compiles
        "wall_s": wall_s,
        "not_matched": [
            "Brax's policy learns log std per action like ours but samples from its own "
            "distribution code; ours is Gaussian in the pre-clip action (same count of FLOPs)",
            "Brax's env wrappers (EpisodeWrapper, AutoResetWrapper replaying the first reset) instead "
            "of our VecEnv (fresh resets under one lax.cond)",
            "Brax updates observation statistics before the epochs, we after",
            "Brax does not bootstrap time-limit truncations with V(final obs) (bootstrap_on_timeout needs "
            "an info['time_out'] its own wrappers do not set); we do",
            "Brax's Adam has no epsilon change (1e-8) and its loss/optimizer code is its own",
        ],
    }


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict:
    """Runs the suite with ``key=value`` items; writes and returns the results.

    In one process, on one task and one set of settings: the raw vectorized env
    (random actions, jitted `lax.scan`), the training iteration of every trainer row
    (`_throughput_configs`), timed interleaved after one warm-up each, then Brax's
    own PPO. Raises `ConfigError` for bad input before anything runs.
    """
    bench, cfg, config_items = parse(items)
    info, t_start = measure.start("throughput", log)
    skipped = {n: "not in rows=" for n in ROWS if n not in bench["rows"]}
    rows_wanted = list(bench["rows"])
    steps = cfg.steps_per_iteration
    rows = _compile_rows(cfg, config_items, rows_wanted, log)
    for name, row in rows.items():
        log(f"[bench] warm-up call, {name} ...")
        t0 = time.perf_counter()
        row["args"] = jax.block_until_ready(row["call"](row["args"]))
        row["warmup_s"] = time.perf_counter() - t0
        row["times"] = []
    names = list(rows)

    def timed_round(i: int) -> None:
        order = names if i % 2 == 0 else names[::-1]
        for name in order:
            row = rows[name]
            if name in ("sac", "coherent_sac") and i >= bench["sac_iterations"]:
                continue
            t0 = time.perf_counter()
            row["args"] = jax.block_until_ready(row["call"](row["args"]))
            row["times"].append(time.perf_counter() - t0)
        log(
            f"[bench] round {i + 1}/{bench['iterations']}: "
            + ", ".join(f"{n} {rows[n]['times'][-1]:.3f} s" for n in order if len(rows[n]["times"]) > i)
        )

    rss_ours = measure.peak_rss_bytes()  # our rows compiled and warm, before Brax
    brax_result = None
    if "brax_ppo" in rows_wanted:  # our rounds run between Brax's warm epochs
        load_brax = measure.load_average()
        brax_result = _brax_ppo(cfg, bench["iterations"], log, between_epochs=timed_round)
        brax_result["load_average_start"] = load_brax
    else:
        for i in range(bench["iterations"]):
            timed_round(i)
    results = _row_results(rows, steps)
    rows.clear()
    if brax_result is not None:
        results["brax_ppo"] = brax_result
    figures = {
        "env_steps_per_iteration": steps,
        "rows": results,
        "skipped": skipped,
        "ratios": _ratios(results),
        "targets": {"ppo_over_brax_ppo": 1.0, "training_over_raw_env": 0.6},
        "peak_rss_bytes_after_ours": rss_ours,
        "peak_rss_bytes_end": measure.peak_rss_bytes(),
    }
    settings = {"config": to_dict(cfg), **bench}
    return measure.finish("throughput", info, t_start, settings, figures, bench["out"], log)


def _compile_rows(cfg: Config, config_items: list[str], rows_wanted: list[str], log) -> dict[str, dict]:
    """The raw env rollout and every trainer row's iteration, compiled: per row its call,
    arguments, compile time and XLA memory (and config)."""
    shape = f"{cfg.env}, {cfg.num_envs} envs x {cfg.unroll_length} steps"
    env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    rows: dict[str, dict] = {}

    log(f"[bench] compiling the raw env rollout ({shape}, random actions) ...")
    rollout = _raw_rollout(env)
    key = jax.random.PRNGKey(cfg.seed)
    env_state = jax.jit(env.reset)(key)
    raw_fn = lambda s, k: rollout(s, k, cfg.unroll_length)  # noqa: E731
    compiled, compile_s = measure.compile_timed(raw_fn, env_state, key)
    rows["raw_env"] = {
        "call": lambda args, c=compiled: c(*args)[:2],
        "args": (env_state, key),
        "compile_s": compile_s,
        "memory": measure.memory(compiled),
    }
    log(f"[bench]   compiled in {compile_s:.1f} s")

    configs = _throughput_configs(cfg, config_items, rows_wanted)
    for name, run_cfg in configs.items():
        log(f"[bench] compiling the {run_cfg.algo} iteration, explore={run_cfg.explore} ({shape}) ...")
        trainer = make_trainer(run_cfg, env=env, eval_env=env)  # no evaluation runs here
        state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
        compiled, compile_s = measure.compile_timed(trainer.iteration, state)
        mem = measure.memory(compiled)
        log(f"[bench]   compiled in {compile_s:.1f} s; peak memory {measure.peak_mb(mem)} MB")
        rows[name] = {
            "call": lambda args, c=compiled: (c(*args)[0],),
            "args": (state,),
            "compile_s": compile_s,
            "memory": mem,
            "config": to_dict(run_cfg),
        }
    return rows


def _row_results(rows: dict[str, dict], steps: int) -> dict[str, Any]:
    """Each timed row's figures: the median and best iteration, env steps/s, compile and memory."""
    results: dict[str, Any] = {}
    for name, row in rows.items():
        median = statistics.median(row["times"])
        results[name] = {
            "compile_s": row["compile_s"],
            "memory": row["memory"],
            "warmup_s": row["warmup_s"],
            "iteration_s": row["times"],
            "iteration_s_median": median,
            "env_steps_per_s": steps / median,
            # The fastest iteration: what the row reaches when the shared machine lets it.
            "env_steps_per_s_best": steps / min(row["times"]),
            **({"config": row["config"]} if "config" in row else {}),
        }
    return results


def _ratios(results: dict[str, Any]) -> dict[str, float]:
    """Each row's rate over the raw env's, and the pairs the suite compares."""
    raw = results["raw_env"]["env_steps_per_s"]
    ratios = {
        f"{name}_over_raw_env": results[name]["env_steps_per_s"] / raw
        for name in ("ppo", "coherent_ppo", "sac", "coherent_sac", "brax_ppo")
        if name in results
    }
    for a, b in (
        ("ppo", "brax_ppo"),
        ("coherent_ppo", "brax_ppo"),
        ("coherent_ppo", "ppo"),
        ("coherent_sac", "sac"),
    ):
        if a in results and b in results:
            ratios[f"{a}_over_{b}"] = results[a]["env_steps_per_s"] / results[b]["env_steps_per_s"]
    return ratios


_ROW_LABELS = {
    "raw_env": "raw env (random actions)",
    "ppo": "PPO (ours)",
    "coherent_ppo": "Coherent-PPO (ours)",
    "sac": "SAC (ours)",
    "coherent_sac": "Coherent-SAC (ours)",
    "brax_ppo": "Brax PPO",
}


def format_table(result: dict) -> str:
    """The human-readable summary of `run`'s result."""
    cfg = result["settings"]["config"]
    rows, ratios = result["rows"], result["ratios"]
    hidden = ",".join(map(str, cfg["policy_hidden"]))
    lines = [
        f"throughput bench: {cfg['env']}, {cfg['num_envs']} envs x {cfg['unroll_length']} steps "
        f"({result['env_steps_per_iteration']} env steps per iteration), "
        f"PPO {cfg['ppo']['num_epochs']} epochs x {cfg['ppo']['num_minibatches']} minibatches, "
        f"policy/value [{hidden}] {cfg['activation']}",
        measure.machine_line(result),
        "",
        f"  {'row':<27}{'compile s':>10}{'iter s':>9}{'env steps/s':>13}{'x raw':>7}{'best':>9}"
        f"{'peak MB':>10}",
    ]
    raw = rows["raw_env"]["env_steps_per_s"]
    for name, label in _ROW_LABELS.items():
        if name not in rows:
            lines.append(f"  {label:<27}  skipped: {result['skipped'].get(name, '')}")
            continue
        e = rows[name]
        mem = measure.peak_mb(e.get("memory"))
        lines.append(
            f"  {label:<27}{e['compile_s']:>10.1f}{e['iteration_s_median']:>9.3f}"
            f"{e['env_steps_per_s']:>13,.0f}{e['env_steps_per_s'] / raw:>7.2f}"
            f"{e['env_steps_per_s_best']:>9,.0f}{mem:>10}"
        )
    lines.append("  (iter s and env steps/s: median; best: the fastest iteration)")
    lines.append("")
    labels = {**_ROW_LABELS, "brax_ppo": "Brax PPO"}
    targets = {"ppo_over_brax_ppo": 1.0, "ppo_over_raw_env": 0.6}
    for key, value in ratios.items():
        a, b = key.split("_over_")
        target = f" (target >= {targets[key]})" if key in targets else ""
        lines.append(f"  {labels[a]} / {labels.get(b, b)}: {value:.2f}x{target}")
    lines.append(
        f"  peak memory: XLA estimate per compiled program (ours); process peak RSS "
        f"{measure.mb(result['peak_rss_bytes_after_ours'])} MB after compiling our rows, "
        f"{measure.mb(result['peak_rss_bytes_end'])} MB at the end"
    )
    if "brax_ppo" in rows:
        b = rows["brax_ppo"]
        lines.append(
            f"  Brax PPO: compile = epochs' time above the steady one ({b['epoch_s'][0]:.1f} s, "
            f"{b['epoch_s'][1]:.1f} s for the first two); "
            f"setup (reset, init) {b['setup_s']:.1f} s; our rounds ran between Brax's warm epochs"
        )
    return "\n".join(lines)

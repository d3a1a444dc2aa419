"""The ``coherent`` suite: ``python -m benchmarks coherent [key=value ...]``.

Measures, in one process and on one set of settings, what coherent exploration
costs next to Gaussian action noise:

1. *Training throughput.* The real jitted PPO iteration (`OnPolicyTrainer`) with
   ``explore=action`` and ``explore=coherent`` on the same task, envs, unroll and
   network. Compile time is reported apart. After one warm-up iteration each, the
   two are timed interleaved (A B, B A, A B, ...) so that a load change on a shared
   machine hits both, and the median iteration time gives env steps/s. Peak memory
   of each compiled iteration comes from XLA's ``memory_analysis()``, also for
   ``remat=true``.
2. *The filter alone.* `coherent_jax.exploration.coherent.filter.log_marginals` (p
   independent (q+1)-dimensional Kalman filters, docs/design.md §3) against
   `reference.dense_log_marginals`, the thesis's recursion (4.33)-(4.49) over the flattened
   p(q+1) weight vector, forward and forward+gradient, with a check that both give the
   same log-probabilities.
3. *The loss's segment log-prob.* ``strategy.log_prob`` as the trainer's loss
   calls it (vmapped over a minibatch of env segments, with its gradient), for
   coherent and for action noise.

4. *Long chains* (`benchmarks.chains`): the same interleaved pair at
   ``preset=thesis`` (4 envs x 1,000-step buffers) and with ``coherent.gradient=episode``
   (the episode prefix re-inferred in the loss); ``chains=none`` skips them.

Settings are ``key=value``: every training key except ``explore`` and ``remat``
(the suite sets those), plus `KEYS`.
The results go to a JSON file (default ``bench_results/coherent.json``), written
atomically.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from benchmarks import IGNORED, measure
from benchmarks.chains import CHAINS, bench_chains, chain_config, format_chains
from benchmarks.filter_cost import bench_filter
from coherent_jax.agents.onpolicy import OnPolicyTrainer
from coherent_jax.config import Config, cli, to_dict, validate, with_values
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.exploration.base import Segment
from coherent_jax.run import devices

_count = cli.int_at_least(1)
# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "over 15 min (stopped at 900 s in its q=256 filter rows, before its long-chain rows)"
KEYS: dict[str, cli.Key] = {
    "iterations": cli.Key(5, _count, "an integer >= 1", "timed PPO iterations per strategy"),
    "out": cli.Key(
        "bench_results/coherent.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
    "filter_q": cli.Key(
        [64, 256], cli.int_list(1), "a list of integers >= 1, e.g. [64,256]", "trunk widths q"
    ),
    "filter_p": cli.Key(6, _count, "an integer >= 1", "action dimensions p of the filter benchmark"),
    "filter_T": cli.Key(256, _count, "an integer >= 1", "sequence length T of the filter benchmark"),
    "filter_batch": cli.Key(8, _count, "an integer >= 1", "sequences per call (vmapped)"),
    "filter_repeats": cli.Key(5, _count, "an integer >= 1", "timed calls per filter measurement"),
    "dense_budget_s": cli.Key(
        60.0, cli.positive_float, "a number > 0", "fewer dense repeats if they would take longer than this"
    ),
    "dense_mem_gb": cli.Key(
        3.0,
        cli.positive_float,
        "a number > 0",
        "dense gradient: checkpoint the scan (then map over the batch) above this peak memory",
    ),
    "chains": cli.Key(
        list(CHAINS),
        lambda text: [] if text.strip() in ("none", "[]") else cli.choice_list(CHAINS)(text),
        "a non-empty list of " + ", ".join(CHAINS) + ", or none",
        "long-chain rows (benchmarks/chains.py): preset=thesis, and coherent.gradient=episode",
    ),
    "chain_iterations": cli.Key(
        3,
        _count,
        "an integer >= 1",
        "timed PPO iterations per long-chain row (episode: rounded up to whole episode cycles)",
    ),
    "seg_envs": cli.Key(8, _count, "an integer >= 1", "env segments in the log_prob minibatch"),
    "seg_repeats": cli.Key(10, _count, "an integer >= 1", "timed calls per log_prob measurement"),
}
# Training keys the suite sets itself: it runs both strategies, and remat on and off.
FIXED: dict[str, str | None] = {"explore": None, "coherent.remat": None}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings and training config; `ConfigError` in one line for bad input.

    The config is checked with both strategies the suite runs, so that a setting
    one of them refuses stops the suite before it compiles anything.
    """
    parsed = cli.parse_command(items, KEYS, command="the coherent suite", fixed=FIXED, ignored=IGNORED)
    for explore in ("action", "coherent"):
        validate(dataclasses.replace(parsed.config, explore=explore))
    for chain in parsed.settings["chains"]:
        chain_config(parsed.config, chain)
    return parsed


def _bench_training(cfg: Config, iterations: int, log, remat_row: bool = True) -> tuple[dict, dict]:
    """Compiles and times the PPO iteration for both strategies (and compiles the filter
    form with remat for its memory, with ``remat_row``); returns (results, trainers)."""
    num_devices = devices.resolve_num_devices(cfg.num_devices, cfg.env)
    shape = f"{cfg.env}, {cfg.num_envs} envs x {cfg.unroll_length} steps, {num_devices} device(s)"
    # One env object for all trainers (building an MJX model takes seconds); no
    # evaluation runs here, so it also stands in for the evaluation env.
    env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    runs: dict[str, dict] = {}
    rows = [("action", "action", False), ("coherent", "coherent", False)]
    for name, explore, remat in rows + ([("coherent_remat", "coherent", True)] if remat_row else []):
        # The remat row is the sequential-filter form of the loss with its scan
        # rematerialised, whose memory grows linearly with the segment (the joint form's
        # single block grows as T^2), compiled for its memory.
        inference = "filter" if remat else cfg.coherent.inference
        run_cfg = with_values(
            cfg, {"explore": explore, "coherent.remat": remat, "coherent.inference": inference}
        )
        if remat and cfg.coherent.gradient == "episode":  # the filter form has no episode mode
            run_cfg = with_values(run_cfg, {"coherent.gradient": "exact"})
        log(f"[bench] compiling the {cfg.algo} iteration, explore={explore} remat={remat} ({shape}) ...")
        trainer = OnPolicyTrainer(run_cfg, env=env, eval_env=env)
        # (The filter form's carry holds a belief, the joint exact form's does not: each
        # row starts from its own state.)
        # With several devices (num_devices) the envs are split over them as in training.
        state, shardings = devices.init_state(
            trainer, jax.random.PRNGKey(cfg.seed), num_devices, cfg.num_envs
        )
        t0 = time.perf_counter()
        step = devices.compile_iteration(trainer, state, shardings)
        compile_s = time.perf_counter() - t0
        mem = measure.memory(step)
        log(f"[bench]   compiled in {compile_s:.1f} s; peak memory {measure.peak_mb(mem)} MB")
        if remat:  # compiled only for its memory
            trainer = state = step = None
        runs[name] = {"trainer": trainer, "state": state, "step": step, "compile_s": compile_s, "memory": mem}

    timed = ("action", "coherent")
    for name in timed:
        log(f"[bench] warm-up iteration, explore={name} ...")
        run = runs[name]
        t0 = time.perf_counter()
        run["state"], _ = jax.block_until_ready(run["step"](run["state"]))
        run["warmup_s"] = time.perf_counter() - t0
        run["times"] = []

    def on_metrics(name, metrics):
        runs[name]["updates_applied"].append(float(jnp.mean(metrics["train/updates_applied"])))

    for name in timed:
        runs[name]["updates_applied"] = []
    measure.time_interleaved(runs, timed, iterations, log, on_metrics)

    steps = cfg.num_envs * cfg.unroll_length
    results: dict[str, Any] = {}
    for name, run in runs.items():
        entry = {"compile_s": run["compile_s"], "memory": run["memory"]}
        if name in timed:
            median = statistics.median(run["times"])
            entry.update(
                warmup_iteration_s=run["warmup_s"],
                iteration_s=run["times"],
                iteration_s_median=median,
                env_steps_per_s=steps / median,
                env_steps_per_s_total=len(run["times"]) * steps / sum(run["times"]),
                updates_applied=run["updates_applied"],
            )
        results[name] = entry
    results["env_steps_per_iteration"] = steps
    results["num_devices"] = num_devices
    results["ratio_coherent_over_action"] = (
        results["coherent"]["env_steps_per_s"] / results["action"]["env_steps_per_s"]
    )
    peaks = {n: measure.peak(results[n]["memory"]) for n in runs}
    if remat_row and all(peaks.values()):
        results["memory_ratio_coherent_over_action"] = peaks["coherent"] / peaks["action"]
        results["memory_ratio_remat_over_coherent"] = peaks["coherent_remat"] / peaks["coherent"]
    trainers = {n: (runs[n]["trainer"], runs[n]["state"]) for n in timed}
    return results, trainers


# ------------------------------------------------- 3. the loss's segment log-prob
def _bench_segment_log_prob(cfg: Config, bench: dict, trainers: dict, log) -> dict:
    envs, num_steps, repeats = bench["seg_envs"], cfg.unroll_length, bench["seg_repeats"]
    results: dict[str, Any] = {"envs": envs, "T": num_steps, "repeats": repeats}
    for name, (trainer, state) in trainers.items():
        strategy = trainer.strategy
        params, hparams = state.params.policy, state.hparams.explore
        obs_size, p = trainer.env.observation_size, trainer.env.action_size
        k_obs, k_act, k_carry = jax.random.split(jax.random.PRNGKey(cfg.seed), 3)
        obs = jax.random.normal(k_obs, (envs, num_steps, obs_size))
        actions = 0.5 * jax.random.normal(k_act, (envs, num_steps, p))
        first = jnp.zeros((envs, num_steps), bool).at[:, 0].set(True)
        carry0 = strategy.init_carry(k_carry, params, hparams, envs)
        segments = jax.vmap(strategy.log_prob, in_axes=(None, None, 0))  # env-major segments

        def forward(params, hparams, carry0, obs, actions, first, segments=segments):
            seg = segments(params, hparams, Segment(obs, actions, first, carry0))
            return seg.log_prob, seg.entropy

        def loss(params, hparams, carry0, obs, actions, first, segments=segments):
            seg = segments(params, hparams, Segment(obs, actions, first, carry0))
            return jnp.mean(seg.log_prob) + jnp.mean(seg.entropy)

        args = (params, hparams, carry0, obs, actions, first)
        log(f"[bench] strategy.log_prob explore={name}: {envs} envs x {num_steps} steps, compiling ...")
        fwd, fwd_compile_s = measure.compile_timed(forward, *args)
        grad, grad_compile_s = measure.compile_timed(jax.value_and_grad(loss), *args)
        jax.block_until_ready(fwd(*args))
        jax.block_until_ready(grad(*args))
        fwd_times = measure.time_calls(fwd, args, repeats)
        grad_times = measure.time_calls(grad, args, repeats)
        results[name] = {
            "forward_ms": 1e3 * statistics.median(fwd_times),
            "grad_ms": 1e3 * statistics.median(grad_times),
            "compile_forward_s": fwd_compile_s,
            "compile_grad_s": grad_compile_s,
            "memory_grad": measure.memory(grad),
        }
        log(
            f"[bench]   forward {results[name]['forward_ms']:.2f} ms, "
            f"forward+gradient {results[name]['grad_ms']:.2f} ms"
        )
    results["ratio_forward_coherent_over_action"] = (
        results["coherent"]["forward_ms"] / results["action"]["forward_ms"]
    )
    results["ratio_grad_coherent_over_action"] = results["coherent"]["grad_ms"] / results["action"]["grad_ms"]
    return results


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict:
    """Runs the suite with ``key=value`` items; writes and returns the results.

    Raises `ConfigError` for bad input before anything runs.
    """
    bench, cfg, _ = parse(items)
    info, t_start = measure.start("coherent", log)
    training, trainers = _bench_training(cfg, bench["iterations"], log)
    segment = _bench_segment_log_prob(cfg, bench, trainers, log)
    del trainers
    figures = {"training": training, "segment_log_prob": segment, "filter": bench_filter(cfg, bench, log)}
    figures["chains"] = bench_chains(cfg, bench["chains"], bench["chain_iterations"], _bench_training, log)
    settings = {"config": to_dict(cfg), **bench}
    return measure.finish("coherent", info, t_start, settings, figures, bench["out"], log)


def format_table(result: dict) -> str:
    """The human-readable summary of `run`'s result."""
    cfg = result["settings"]["config"]
    tr, seg, filt = result["training"], result["segment_log_prob"], result["filter"]
    hidden = ",".join(map(str, cfg["policy_hidden"]))
    lines = [
        f"coherent bench: {cfg['env']}, {cfg['num_envs']} envs x {cfg['unroll_length']} steps, "
        f"{cfg['algo']} {cfg['ppo']['num_epochs']} epochs x {cfg['ppo']['num_minibatches']} minibatches, "
        f"policy [{hidden}], coherent.beta={cfg['coherent']['beta']}, "
        f"coherent.inference={cfg['coherent']['inference']}",
        measure.machine_line(result),
        "",
        f"1. PPO iteration (median of {len(tr['action']['iteration_s'])}, interleaved)",
        f"  {'explore':<22}{'compile s':>10}{'iter s':>10}{'env steps/s':>13}{'peak MB':>11}",
    ]
    for name, label in (
        ("action", "action"),
        ("coherent", "coherent"),
        ("coherent_remat", "coherent filter remat"),
    ):
        e = tr[name]
        iter_s = f"{e['iteration_s_median']:.3f}" if "iteration_s_median" in e else "-"
        sps = f"{e['env_steps_per_s']:,.0f}" if "env_steps_per_s" in e else "-"
        lines.append(
            f"  {label:<22}{e['compile_s']:>10.1f}{iter_s:>10}{sps:>13}{measure.peak_mb(e['memory']):>11}"
        )
    ratio = f"  coherent/action: throughput {tr['ratio_coherent_over_action']:.2f}x"
    if "memory_ratio_coherent_over_action" in tr:
        ratio += (
            f", peak memory {tr['memory_ratio_coherent_over_action']:.2f}x"
            f" (filter+remat / joint {tr['memory_ratio_remat_over_coherent']:.2f}x)"
        )
    lines += [ratio, ""]
    lines += [
        f"2. filter log p(a_t | history): p={filt['p']}, T={filt['T']}, batch {filt['batch']} (vmapped), "
        f"{filt['dtype']}, beta={filt['beta']}",
        f"  {'q':>5} {'method':<7}{'forward ms':>12}{'fwd+grad ms':>13}{'grad peak MB':>14}{'reps':>6}"
        "  gradient",
    ]
    for case in filt["cases"]:
        for method in ("block", "dense"):
            e = case[method]
            reps = f"{e['repeats']}{'*' if e['first_call_timed'] else ''}"
            lines.append(
                f"  {case['q']:>5} {method:<7}{e['forward_ms']:>12.2f}{e['grad_ms']:>13.2f}"
                f"{measure.peak_mb(e['memory_grad']):>14}{reps:>6}  {e['grad_mode']}"
            )
        lines.append(
            f"  {'':>5} speedup dense/block: forward {case['speedup_forward']:.1f}x, "
            f"fwd+grad {case['speedup_grad']:.1f}x; max |logp diff| {case['max_abs_logp_diff']:.1e} "
            f"(|logp| <= {case['max_abs_logp']:.1f}), grad rel diff {case['max_rel_grad_diff']:.1e}"
        )
    if any(case[m]["first_call_timed"] for case in filt["cases"] for m in ("block", "dense")):
        lines.append("  * one call, the first after compiling (a round took longer than dense_budget_s)")
    lines.append("")
    lines += [
        f"3. strategy.log_prob as in the loss: vmap over {seg['envs']} envs x {seg['T']} steps "
        f"(median of {seg['repeats']})",
        f"  {'explore':<22}{'forward ms':>12}{'fwd+grad ms':>13}",
    ]
    for name in ("action", "coherent"):
        lines.append(f"  {name:<22}{seg[name]['forward_ms']:>12.2f}{seg[name]['grad_ms']:>13.2f}")
    lines += [
        f"  coherent/action: forward {seg['ratio_forward_coherent_over_action']:.1f}x, "
        f"fwd+grad {seg['ratio_grad_coherent_over_action']:.1f}x",
    ]
    chains = format_chains(result.get("chains", {}))
    return "\n".join(lines + ([""] + chains if chains else []))

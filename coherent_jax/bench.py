"""Benchmarks: ``python -m coherent_jax.bench [throughput|coherent|sac] [key=value ...]``.

(The ``sac`` suite lives in `coherent_jax.bench_sac`.) The ``throughput`` suite, the
default, is `run_throughput_bench`: in one process on one task and one set of
settings, the raw vectorized env rate, the training rate of PPO, Coherent-PPO, SAC
and Coherent-SAC, and Brax's own PPO trainer on the same env and batch layout, with
compile times apart, peak memory and the ratios.

The ``coherent`` suite measures, in one process and on one set of settings, what
coherent exploration costs next to Gaussian action noise:

1. *Training throughput.* The real jitted PPO iteration (`OnPolicyTrainer`) with
   ``explore=action`` and ``explore=coherent`` on the same task, envs, unroll and
   network. Compile time is reported apart. After one warm-up iteration each, the
   two are timed interleaved (A B, B A, A B, ...) so that a load change on a shared
   machine hits both, and the median iteration time gives env steps/s. Peak memory
   of each compiled iteration comes from XLA's ``memory_analysis()``, also for
   ``remat=true``.
2. *The filter alone.* `coherent.log_marginals` (p independent (q+1)-dimensional
   Kalman filters, DESIGN.md §2) against `dense_log_marginals` below, the thesis's
   recursion (4.33)-(4.49) over the flattened p(q+1) weight vector, forward and
   forward+gradient, with a check that both give the same log-probabilities.
3. *The loss's segment log-prob.* ``strategy.log_prob`` as the trainer's loss
   calls it (vmapped over a minibatch of env segments, with its gradient), for
   coherent and for action noise.

Settings are ``key=value``: every `Config` key except ``explore`` and ``remat``
(the suite sets those), plus the keys in `BENCH_KEYS`. A bad key or value is one
line on stderr and exit status 2, before anything runs or is written. The results
go to a JSON file (default ``bench_results/coherent.json``), written atomically.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import Config, ConfigError, parse_overrides, to_dict

SUITES = ("throughput", "coherent", "sac")  # sac: coherent_jax/bench_sac.py
DEFAULT_SUITE = "throughput"  # what ``python -m coherent_jax.bench`` runs with no suite named
# Config keys the coherent suite sets itself: it runs both strategies, and remat on and off.
_SET_BY_SUITE = ("explore", "remat")
_LOG_2PI = math.log(2.0 * math.pi)


# ------------------------------------------------------------------ settings
def _parse_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise ValueError
    return value


def _parse_pos_float(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError
    return value


def _parse_int_list(text: str) -> list[int]:
    items = [s.strip() for s in text.strip().strip("[]").split(",") if s.strip()]
    if not items:
        raise ValueError
    return [_parse_int(s) for s in items]


def _parse_path(text: str) -> str:
    if not text or Path(text).is_dir():
        raise ValueError
    return text


@dataclasses.dataclass(frozen=True)
class BenchKey:
    default: Any
    parse: Callable[[str], Any]
    allowed: str
    help: str


BENCH_KEYS: dict[str, BenchKey] = {
    "iterations": BenchKey(5, _parse_int, "an integer >= 1", "timed PPO iterations per strategy"),
    "out": BenchKey("bench_results/coherent.json", _parse_path, "a file path", "where the JSON goes"),
    "filter_q": BenchKey(
        [64, 256], _parse_int_list, "a list of integers >= 1, e.g. [64,256]", "trunk widths q"
    ),
    "filter_p": BenchKey(6, _parse_int, "an integer >= 1", "action dimensions p of the filter benchmark"),
    "filter_T": BenchKey(256, _parse_int, "an integer >= 1", "sequence length T of the filter benchmark"),
    "filter_batch": BenchKey(8, _parse_int, "an integer >= 1", "sequences per call (vmapped)"),
    "filter_repeats": BenchKey(5, _parse_int, "an integer >= 1", "timed calls per filter measurement"),
    "dense_budget_s": BenchKey(
        60.0, _parse_pos_float, "a number > 0", "fewer dense repeats if they would take longer than this"
    ),
    "dense_mem_gb": BenchKey(
        3.0,
        _parse_pos_float,
        "a number > 0",
        "dense gradient: checkpoint the scan (then map over the batch) above this peak memory",
    ),
    "seg_envs": BenchKey(8, _parse_int, "an integer >= 1", "env segments in the log_prob minibatch"),
    "seg_repeats": BenchKey(10, _parse_int, "an integer >= 1", "timed calls per log_prob measurement"),
}


def _parse_bool(text: str) -> bool:
    if text.lower() in ("true", "1", "yes"):
        return True
    if text.lower() in ("false", "0", "no"):
        return False
    raise ValueError


# Rows of the throughput suite besides the raw env; brax_ppo is Brax's own trainer.
THROUGHPUT_ROWS = ("ppo", "coherent_ppo", "sac", "coherent_sac", "brax_ppo")


def _parse_choice_list(text: str, choices: Sequence[str]) -> list[str]:
    items = [s.strip() for s in text.strip().strip("[]").split(",") if s.strip()]
    if not items or any(item not in choices for item in items):
        raise ValueError
    return [c for c in choices if c in items]


# The throughput suite's own keys (issue 6, part 3).
THROUGHPUT_KEYS: dict[str, BenchKey] = {
    "iterations": BenchKey(9, _parse_int, "an integer >= 1", "timed iterations per row (after one warm-up)"),
    "out": BenchKey("bench_results/throughput.json", _parse_path, "a file path", "where the JSON goes"),
    "sac_iterations": BenchKey(
        2,
        _parse_int,
        "an integer >= 1",
        "timed iterations of the SAC rows (UTD 1: num_envs * unroll_length updates each, slow on CPU), "
        "in the first rounds",
    ),
    "rows": BenchKey(
        list(THROUGHPUT_ROWS),
        lambda text: _parse_choice_list(text, THROUGHPUT_ROWS),
        "a non-empty list of " + ", ".join(THROUGHPUT_ROWS),
        "rows besides the raw env (always run); sac rows need coherent_jax.agents.sac",
    ),
}
SUITE_KEYS: dict[str, dict[str, BenchKey]] = {"coherent": BENCH_KEYS, "throughput": THROUGHPUT_KEYS}
# Config keys each suite sets itself (the throughput suite runs every algorithm and strategy).
SET_BY_SUITE: dict[str, tuple[str, ...]] = {"coherent": _SET_BY_SUITE, "throughput": ("algo", "explore")}


def parse_bench_overrides(
    overrides: Sequence[str], suite: str = "coherent"
) -> tuple[Config, dict[str, Any], list[str]]:
    """Splits ``key=value`` strings into a validated `Config` and the bench settings of ``suite``.

    Returns (config, bench settings, the config overrides as given). Raises
    `ConfigError` with a one-line message naming the bad key or value.
    """
    keys, set_by_suite = SUITE_KEYS[suite], SET_BY_SUITE[suite]
    bench = {k: v.default for k, v in keys.items()}
    config_items = []
    config_keys = {f.name for f in dataclasses.fields(Config)}
    for item in overrides:
        if "=" not in item or item.startswith("="):
            raise ConfigError(f"malformed override {item!r}: expected key=value")
        key, text = (s.strip() for s in item.split("=", 1))
        if key in set_by_suite:
            raise ConfigError(
                f"invalid key {key!r}: the {suite} suite sets it itself "
                f"(allowed: any key except {', '.join(set_by_suite)})"
            )
        if key in keys:
            spec = keys[key]
            try:
                bench[key] = spec.parse(text)
            except ValueError:
                raise ConfigError(f"invalid value for {key!r}: {text!r} (allowed: {spec.allowed})") from None
        elif key in config_keys:
            config_items.append(item)
        else:
            valid = sorted((config_keys - set(set_by_suite)) | set(keys))
            raise ConfigError(f"unknown key {key!r}; valid keys: {', '.join(valid)}")
    return parse_overrides(config_items), bench, config_items


# ------------------------------------------------------- the dense recursion
def dense_log_marginals(x, a, first, mu, w_std, action_std, beta, checkpoint_chunk: int = 0):
    """The thesis's filter (4.33)-(4.49) on the flattened weights, as a reference.

    The weights are one vector w in R^(p(q+1)) laid out as in (4.30), the p rows of
    W row by row and then the p biases, and X_t in R^(p x p(q+1)) is (4.31),
    [I_p (x) x_t', I_p], so a_t | w_t ~ N(X_t w_t, Lambda_a^-1) (4.32). The belief
    alpha(w_t) = N(v_t, L_t^-1) is kept in covariance form, P = L_t^-1, and
    conditioning on a_t uses the Woodbury form of (4.41)-(4.42):

        S = Lambda_a^-1 + X P X'           log p(a_t | history) = log N(a_t; X v, S)   (4.37/4.49)
        u = v + P X' S^-1 (a_t - X v)      Sigma = P - P X' S^-1 X P                   (4.41-4.42)
        v <- (1-beta) u + beta mu          P <- (2beta - beta^2) Lambda^-1 + (1-beta)^2 Sigma  (4.45-4.46)

    with an O(p^3) solve of S and O(p (p(q+1))^2) matrix products per step, and, as
    in the thesis, no re-symmetrisation of P (a transpose of the p(q+1)-square matrix
    per step made it about four times slower on CPU). That is the cheapest dense form
    (the information form of (4.42) inverts a p(q+1)-square matrix per step), so it
    flatters the dense side, except where its gradient must be checkpointed to fit
    in memory, which costs about one more forward pass (the bench records this).

    Same contract as `coherent.log_marginals`: x [T, q], a [T, p], first [T], mu and
    w_std [p, q+1] (bias last), action_std [p]; t = 0 always starts from the prior.
    ``checkpoint_chunk > 0`` rematerialises the scan in chunks of that many steps
    (only the belief at each chunk start is kept for the backward pass), so the
    gradient fits in memory when p(q+1) is large.

    Returns:
      logp [T].
    """
    import jax
    import jax.numpy as jnp

    num_steps, q = x.shape
    p = a.shape[-1]
    eye_p = jnp.eye(p, dtype=x.dtype)
    mean0 = jnp.concatenate([mu[:, :q].reshape(-1), mu[:, q]])  # (4.30)
    cov0 = jnp.diag(jnp.concatenate([w_std[:, :q].reshape(-1), w_std[:, q]]) ** 2)  # Lambda^-1
    noise_cov = jnp.diag(action_std**2)  # Lambda_a^-1
    decay = 1.0 - beta
    innovation = beta * (2.0 - beta)

    def step(belief, inputs):
        x_t, a_t, reset = inputs
        mean = jnp.where(reset, mean0, belief[0])  # (4.33) at an episode start
        cov = jnp.where(reset, cov0, belief[1])
        big_x = jnp.concatenate([jnp.kron(eye_p, x_t[None, :]), eye_p], axis=1)  # (4.31)
        x_cov = big_x @ cov  # X P, [p, D]
        s = noise_cov + x_cov @ big_x.T
        err = a_t - big_x @ mean
        _, logdet = jnp.linalg.slogdet(s)
        logp = -0.5 * (p * _LOG_2PI + logdet + err @ jnp.linalg.solve(s, err))
        s_inv_x_cov = jnp.linalg.solve(s, x_cov)  # S^-1 X P
        post_mean = mean + s_inv_x_cov.T @ err
        post_cov = cov - x_cov.T @ s_inv_x_cov
        new_mean = decay * post_mean + beta * mean0
        new_cov = innovation * cov0 + decay**2 * post_cov
        return (new_mean, new_cov), logp

    reset = jnp.asarray(first, bool).at[0].set(True)
    belief0 = (mean0, cov0)
    if checkpoint_chunk <= 0 or checkpoint_chunk >= num_steps:
        _, logp = jax.lax.scan(step, belief0, (x, a, reset))
        return logp
    chunk = checkpoint_chunk
    while num_steps % chunk:  # largest divisor of T not above the request
        chunk -= 1
    split = lambda z: z.reshape((num_steps // chunk, chunk) + z.shape[1:])

    @jax.checkpoint
    def run_chunk(belief, inputs):
        return jax.lax.scan(step, belief, inputs)

    _, logp = jax.lax.scan(run_chunk, belief0, (split(x), split(a), split(reset)))
    return logp.reshape(num_steps)


def _sample_segments(key, batch, num_steps, q, p, w_std_init, action_std, beta):
    """Inputs for the filter benchmark: actions drawn from the model (4.1-4.5, 4.29).

    x = tanh(N(0, 1)) like a tanh trunk's output, two episodes per sequence (a
    reset at T/2 exercises the prior reset), weights following the chain.
    """
    import jax
    import jax.numpy as jnp

    k_x, k_mu, k_run = jax.random.split(key, 3)
    x = jnp.tanh(jax.random.normal(k_x, (batch, num_steps, q)))
    mu = 0.1 * jax.random.normal(k_mu, (p, q + 1))
    w_std = jnp.full((p, q + 1), w_std_init)
    sigma = jnp.full((p,), action_std)
    first = jnp.zeros((num_steps,), bool).at[0].set(True).at[num_steps // 2].set(True)
    innovation_std = math.sqrt(max(beta * (2.0 - beta), 0.0))

    def one(k, xs):
        def step(w, inputs):
            k_t, x_t, first_t = inputs
            k_w, k_a = jax.random.split(k_t)
            eps = jax.random.normal(k_w, w.shape)
            chained = (1.0 - beta) * w + beta * mu + innovation_std * w_std * eps
            w = jnp.where(first_t, mu + w_std * eps, chained)
            a_t = w @ jnp.append(x_t, 1.0) + sigma * jax.random.normal(k_a, (p,))
            return w, a_t

        _, actions = jax.lax.scan(step, mu, (jax.random.split(k, num_steps), xs, first))
        return actions

    a = jax.vmap(one)(jax.random.split(k_run, batch), x)
    return x, a, jnp.broadcast_to(first, (batch, num_steps)), mu, w_std, sigma, jnp.float32(beta)


# ------------------------------------------------------------------ helpers
def _memory(compiled) -> dict[str, int] | None:
    """Peak memory of a compiled program from XLA (None if the backend has none)."""
    try:
        stats = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if stats is None:
        return None
    fields = {
        "temp_bytes": "temp_size_in_bytes",
        "argument_bytes": "argument_size_in_bytes",
        "output_bytes": "output_size_in_bytes",
        "alias_bytes": "alias_size_in_bytes",
    }
    out = {k: int(getattr(stats, attr, 0) or 0) for k, attr in fields.items()}
    # Donated (aliased) buffers are counted in both arguments and outputs.
    out["peak_bytes"] = out["temp_bytes"] + out["argument_bytes"] + out["output_bytes"] - out["alias_bytes"]
    return out


def _compile(fn, *args):
    import jax

    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - t0


def _time_calls(compiled, args, repeats: int) -> list[float]:
    import jax

    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return times


def _mb(nbytes: int | None) -> str:
    return "-" if nbytes is None else f"{nbytes / 2**20:,.1f}"


def _peak(mem: dict | None) -> int | None:
    return None if mem is None else mem["peak_bytes"]


def _load() -> list[float]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return []


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine()


# ---------------------------------------------------- 1. training throughput
def _bench_training(cfg: Config, iterations: int, log) -> tuple[dict, dict]:
    """Compiles and times the PPO iteration for both strategies; returns (results, trainers)."""
    import jax

    from coherent_jax.agents.onpolicy import OnPolicyTrainer
    from coherent_jax.envs.vec_env import VecEnv

    shape = f"{cfg.env}, {cfg.num_envs} envs x {cfg.unroll_length} steps"
    # One env object for all trainers (building an MJX model takes seconds); no
    # evaluation runs here, so it also stands in for the evaluation env.
    env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    runs: dict[str, dict] = {}
    for name, explore, remat in (
        ("action", "action", False),
        ("coherent", "coherent", False),
        ("coherent_remat", "coherent", True),
    ):
        # The remat row is the sequential-filter form of the loss with its scan
        # rematerialised (remat only applies there), compiled for its memory.
        inference = "filter" if remat else cfg.coherent_inference
        run_cfg = dataclasses.replace(cfg, explore=explore, remat=remat, coherent_inference=inference)
        log(f"[bench] compiling the {cfg.algo} iteration, explore={explore} remat={remat} ({shape}) ...")
        trainer = OnPolicyTrainer(run_cfg, env=env, eval_env=env)
        if remat:  # same state as without remat; only the compiled backward pass differs
            state = runs["coherent"]["state"]
        else:
            state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
        step, compile_s = _compile(trainer.iteration, state)
        mem = _memory(step)
        log(f"[bench]   compiled in {compile_s:.1f} s; peak memory {_mb(_peak(mem))} MB")
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
    for i in range(iterations):
        order = timed if i % 2 == 0 else timed[::-1]
        for name in order:
            run = runs[name]
            t0 = time.perf_counter()
            run["state"], _ = jax.block_until_ready(run["step"](run["state"]))
            run["times"].append(time.perf_counter() - t0)
        log(
            f"[bench] iteration {i + 1}/{iterations}: "
            + ", ".join(f"{n} {runs[n]['times'][-1]:.3f} s" for n in order)
        )

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
            )
        results[name] = entry
    results["env_steps_per_iteration"] = steps
    results["ratio_coherent_over_action"] = (
        results["coherent"]["env_steps_per_s"] / results["action"]["env_steps_per_s"]
    )
    peaks = {n: _peak(results[n]["memory"]) for n in ("action", "coherent", "coherent_remat")}
    if all(peaks.values()):
        results["memory_ratio_coherent_over_action"] = peaks["coherent"] / peaks["action"]
        results["memory_ratio_remat_over_coherent"] = peaks["coherent_remat"] / peaks["coherent"]
    trainers = {n: (runs[n]["trainer"], runs[n]["state"]) for n in timed}
    return results, trainers


# ---------------------------------------------------------- 2. the filter
def _bench_filter(cfg: Config, bench: dict, log) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from coherent_jax.exploration.coherent import log_marginals

    p, num_steps, batch = bench["filter_p"], bench["filter_T"], bench["filter_batch"]
    in_axes = (0, 0, 0, None, None, None, None)

    def forward(impl, chunk=0):
        def f(x, a, first, mu, w_std, action_std, beta):
            single = lambda *args: impl(*args, checkpoint_chunk=chunk) if chunk else impl(*args)
            return jax.vmap(single, in_axes)(x, a, first, mu, w_std, action_std, beta)

        return f

    def with_grad(impl, chunk=0, sequential=False):
        """value and d/d(mu, w_std) of sum log p over the batch."""

        def total(mu, w_std, x, a, first, action_std, beta):
            if sequential:  # one sequence at a time: 1/batch of the memory

                def one(inputs):
                    xi, ai, fi = inputs
                    logp = lambda m, s: jnp.sum(
                        impl(xi, ai, fi, m, s, action_std, beta, checkpoint_chunk=chunk)
                    )
                    return jax.value_and_grad(logp, argnums=(0, 1))(mu, w_std)

                values, (g_mu, g_std) = jax.lax.map(one, (x, a, first))
                return values.sum(), (g_mu.sum(0), g_std.sum(0))
            fwd = forward(impl, chunk)
            logp = lambda m, s: jnp.sum(fwd(x, a, first, m, s, action_std, beta))
            return jax.value_and_grad(logp, argnums=(0, 1))(mu, w_std)

        return total

    cases = []
    for q in bench["filter_q"]:
        inputs = _sample_segments(
            jax.random.PRNGKey(cfg.seed + q), batch, num_steps, q, p, cfg.w_std_init, cfg.action_std, cfg.beta
        )
        x, a, first, mu, w_std, action_std, beta = inputs
        grad_args = (mu, w_std, x, a, first, action_std, beta)
        case: dict[str, Any] = {"q": q, "state_dim": p * (q + 1)}
        outputs = {}
        for method in ("block", "dense"):
            log(f"[bench] filter q={q} {method}: compiling forward and forward+gradient ...")
            impl = log_marginals if method == "block" else dense_log_marginals
            fwd, fwd_compile_s = _compile(forward(impl), *inputs)
            grad_mode = "vmap"
            grad, grad_compile_s = _compile(with_grad(impl), *grad_args)
            tried = [{"mode": grad_mode, "peak_bytes": _peak(_memory(grad)), "compile_s": grad_compile_s}]
            if method == "dense":
                # The dense belief is p(q+1) squared per step and sequence; keeping one per
                # step for the backward pass can exceed the machine, so checkpoint if needed.
                budget = bench["dense_mem_gb"] * 2**30
                chunk = max(1, round(math.sqrt(num_steps)))
                for mode, kwargs in (
                    (f"vmap, checkpoint every {chunk} steps", {"chunk": chunk}),
                    (
                        f"lax.map over the batch, checkpoint every {chunk} steps",
                        {"chunk": chunk, "sequential": True},
                    ),
                ):
                    if (tried[-1]["peak_bytes"] or 0) <= budget:
                        break
                    log(f"[bench]   dense gradient needs {_mb(tried[-1]['peak_bytes'])} MB; trying {mode}")
                    grad, grad_compile_s = _compile(with_grad(impl, **kwargs), *grad_args)
                    grad_mode = mode
                    tried.append(
                        {"mode": mode, "peak_bytes": _peak(_memory(grad)), "compile_s": grad_compile_s}
                    )
            # First calls (warm-up) also estimate how many repeats fit in the budget.
            t0 = time.perf_counter()
            logp = jax.block_until_ready(fwd(*inputs))
            fwd_first = time.perf_counter() - t0
            t0 = time.perf_counter()
            value, grads = jax.block_until_ready(grad(*grad_args))
            grad_first = time.perf_counter() - t0
            repeats, first_call_only = bench["filter_repeats"], False
            if method == "dense":
                # The dense recursion can take minutes: fit the repeats into the budget,
                # and if even one round does not fit, report the first call's time.
                rounds = int(bench["dense_budget_s"] // max(fwd_first + grad_first, 1e-9))
                repeats, first_call_only = max(1, min(repeats, rounds)), rounds == 0
            if first_call_only:
                log(f"[bench] filter q={q} {method}: one round > dense_budget_s; timed the first call")
                fwd_times, grad_times = [fwd_first], [grad_first]
            else:
                log(f"[bench] filter q={q} {method}: timing {repeats} x (forward, forward+gradient) ...")
                fwd_times = _time_calls(fwd, inputs, repeats)
                grad_times = _time_calls(grad, grad_args, repeats)
            outputs[method] = (np.asarray(logp), value, [np.asarray(g) for g in grads])
            case[method] = {
                "forward_ms": 1e3 * statistics.median(fwd_times),
                "grad_ms": 1e3 * statistics.median(grad_times),
                "forward_ms_all": [1e3 * t for t in fwd_times],
                "grad_ms_all": [1e3 * t for t in grad_times],
                "repeats": repeats,
                "first_call_timed": first_call_only,
                "compile_forward_s": fwd_compile_s,
                "compile_grad_s": grad_compile_s,
                "grad_mode": grad_mode,
                "grad_modes_tried": tried,
                "memory_forward": _memory(fwd),
                "memory_grad": _memory(grad),
            }
            log(
                f"[bench]   forward {case[method]['forward_ms']:.2f} ms, "
                f"forward+gradient {case[method]['grad_ms']:.2f} ms"
            )
        (lp_b, _, g_b), (lp_d, _, g_d) = outputs["block"], outputs["dense"]
        case["max_abs_logp_diff"] = float(np.max(np.abs(lp_b - lp_d)))
        case["max_abs_logp"] = float(np.max(np.abs(lp_d)))
        case["max_rel_grad_diff"] = float(
            max(
                np.max(np.abs(gb - gd)) / max(np.max(np.abs(gd)), 1e-30)
                for gb, gd in zip(g_b, g_d, strict=True)
            )
        )
        case["speedup_forward"] = case["dense"]["forward_ms"] / case["block"]["forward_ms"]
        case["speedup_grad"] = case["dense"]["grad_ms"] / case["block"]["grad_ms"]
        log(
            f"[bench] filter q={q}: max |logp block - dense| = {case['max_abs_logp_diff']:.2e} "
            f"(|logp| up to {case['max_abs_logp']:.1f}); speedup dense/block: forward "
            f"{case['speedup_forward']:.1f}x, forward+gradient {case['speedup_grad']:.1f}x"
        )
        cases.append(case)
    return {
        "p": p,
        "T": num_steps,
        "batch": batch,
        "beta": cfg.beta,
        "w_std": cfg.w_std_init,
        "action_std": cfg.action_std,
        "dtype": "float32",
        "dense_form": "covariance (Woodbury) form of (4.33)-(4.49), one p x p solve per step",
        "cases": cases,
    }


# ------------------------------------------------- 3. the loss's segment log-prob
def _bench_segment_log_prob(cfg: Config, bench: dict, trainers: dict, log) -> dict:
    import jax
    import jax.numpy as jnp

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
        segments = jax.vmap(strategy.log_prob, in_axes=(None, None, 0, 0, 0, 0))

        def forward(params, hparams, carry0, obs, actions, first, segments=segments):
            seg = segments(params, hparams, carry0, obs, actions, first)
            return seg.log_prob, seg.entropy

        def loss(params, hparams, carry0, obs, actions, first, segments=segments):
            seg = segments(params, hparams, carry0, obs, actions, first)
            return jnp.mean(seg.log_prob) + jnp.mean(seg.entropy)

        args = (params, hparams, carry0, obs, actions, first)
        log(f"[bench] strategy.log_prob explore={name}: {envs} envs x {num_steps} steps, compiling ...")
        fwd, fwd_compile_s = _compile(forward, *args)
        grad, grad_compile_s = _compile(jax.value_and_grad(loss), *args)
        jax.block_until_ready(fwd(*args))
        jax.block_until_ready(grad(*args))
        fwd_times = _time_calls(fwd, args, repeats)
        grad_times = _time_calls(grad, args, repeats)
        results[name] = {
            "forward_ms": 1e3 * statistics.median(fwd_times),
            "grad_ms": 1e3 * statistics.median(grad_times),
            "compile_forward_s": fwd_compile_s,
            "compile_grad_s": grad_compile_s,
            "memory_grad": _memory(grad),
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


# ------------------------------------------------------ the throughput suite
def sac_available() -> bool:
    """Whether `make_trainer` can build ``algo=sac`` (the SAC trainer module exists)."""
    import importlib.util

    return importlib.util.find_spec("coherent_jax.agents.sac") is not None


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
            sac_items = [i for i in items if i.split("=", 1)[0].strip() not in ("algo", "explore")]
            configs[name] = parse_overrides(
                [
                    "algo=sac",
                    f"explore={explore}",
                    *sac_items,
                    *shared,
                    f"warmup_steps={cfg.steps_per_iteration}",
                ]
            )
    return configs


def _raw_rollout(env):
    """``(env_state, key) -> (env_state, key, reward sum)``: ``unroll_length`` random-action steps."""
    import jax
    import jax.numpy as jnp

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
    import functools

    import jax
    from brax.training.agents.ppo import networks as brax_networks
    from brax.training.agents.ppo import train as brax_train
    from flax import linen

    from coherent_jax.envs.registry import make_brax_env

    steps = cfg.steps_per_iteration
    epochs = iterations + 2
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
        batch_size=cfg.num_envs // cfg.num_minibatches,
        num_minibatches=cfg.num_minibatches,
        num_updates_per_batch=cfg.num_epochs,
        learning_rate=cfg.lr,
        entropy_cost=cfg.ent_coef,
        discounting=cfg.gamma,
        gae_lambda=cfg.gae_lambda,
        clipping_epsilon=cfg.clip_eps,
        max_grad_norm=cfg.max_grad_norm,
        normalize_observations=cfg.normalize_obs,
        normalize_advantage=cfg.normalize_advantages,
        vf_loss_coefficient=cfg.vf_coef,
        # Brax's own env wrappers set no info["time_out"], which bootstrap_on_timeout needs.
        bootstrap_on_timeout=False,
        num_evals=epochs + 1,
        run_evals=False,
        seed=cfg.seed,
    )
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
    env = make_brax_env(cfg.env)
    t0 = time.perf_counter()
    brax_train.train(environment=env, network_factory=network_factory, progress_fn=progress, **settings)
    wall_s = time.perf_counter() - t0
    jax.clear_caches()
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


def _peak_rss_bytes() -> int | None:
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB
    except (ImportError, OSError):
        return None


def run_throughput_bench(overrides: Sequence[str], log: Callable[[str], None] | None = None) -> dict:
    """Runs the ``throughput`` suite with ``key=value`` overrides; writes and returns the results.

    In one process, on one task and one set of settings: the raw vectorized env
    (random actions, jitted `lax.scan`), the training iteration of every trainer row
    (`_throughput_configs`), timed interleaved after one warm-up each, then Brax's
    own PPO. Raises `ConfigError` for a bad override before anything runs.
    """
    cfg, bench, items = parse_bench_overrides(list(overrides), "throughput")
    log = log or (lambda msg: print(msg, flush=True))
    import jax
    import jaxlib

    from coherent_jax.agents import make_trainer
    from coherent_jax.envs.vec_env import VecEnv

    t_start = time.perf_counter()
    device = jax.devices()[0]
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    load_start = _load()
    skipped = {n: "not in rows=" for n in THROUGHPUT_ROWS if n not in bench["rows"]}
    rows_wanted = list(bench["rows"])
    if not sac_available():
        for name in ("sac", "coherent_sac"):
            if name in rows_wanted:
                rows_wanted.remove(name)
                skipped[name] = "coherent_jax.agents.sac is not in this version"
    log(
        f"[bench] throughput suite: jax {jax.__version__} on {device.platform} ({_cpu_model()}, "
        f"{os.cpu_count()} CPUs), load average {load_start}"
    )
    steps = cfg.steps_per_iteration
    shape = f"{cfg.env}, {cfg.num_envs} envs x {cfg.unroll_length} steps"
    env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    rows: dict[str, dict] = {}

    log(f"[bench] compiling the raw env rollout ({shape}, random actions) ...")
    rollout = _raw_rollout(env)
    key = jax.random.PRNGKey(cfg.seed)
    env_state = jax.jit(env.reset)(key)
    raw_fn = lambda s, k: rollout(s, k, cfg.unroll_length)  # noqa: E731
    compiled, compile_s = _compile(raw_fn, env_state, key)
    rows["raw_env"] = {
        "call": lambda args, c=compiled: c(*args)[:2],
        "args": (env_state, key),
        "compile_s": compile_s,
        "memory": _memory(compiled),
    }
    log(f"[bench]   compiled in {compile_s:.1f} s")

    configs = _throughput_configs(cfg, items, rows_wanted)
    for name, run_cfg in configs.items():
        log(f"[bench] compiling the {run_cfg.algo} iteration, explore={run_cfg.explore} ({shape}) ...")
        trainer = make_trainer(run_cfg, env=env, eval_env=env)  # no evaluation runs here
        state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
        compiled, compile_s = _compile(trainer.iteration, state)
        mem = _memory(compiled)
        log(f"[bench]   compiled in {compile_s:.1f} s; peak memory {_mb(_peak(mem))} MB")
        rows[name] = {
            "call": lambda args, c=compiled: (c(*args)[0],),
            "args": (state,),
            "compile_s": compile_s,
            "memory": mem,
            "config": to_dict(run_cfg),
        }

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

    rss_ours = _peak_rss_bytes()  # our rows compiled and warm, before Brax
    brax_result = None
    if "brax_ppo" in rows_wanted:  # our rounds run between Brax's warm epochs
        load_brax = _load()
        brax_result = _brax_ppo(cfg, bench["iterations"], log, between_epochs=timed_round)
        brax_result["load_average_start"] = load_brax
    else:
        for i in range(bench["iterations"]):
            timed_round(i)
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
    rows.clear()
    if brax_result is not None:
        results["brax_ppo"] = brax_result

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
    result = {
        "suite": "throughput",
        "timestamp": started,
        "jax_version": jax.__version__,
        "jaxlib_version": getattr(jaxlib, "__version__", None),
        "device": str(device),
        "platform": device.platform,
        "device_count": jax.device_count(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_start": load_start,
        "load_average_end": _load(),
        "settings": {"config": to_dict(cfg), **bench},
        "env_steps_per_iteration": steps,
        "rows": results,
        "skipped": skipped,
        "ratios": ratios,
        "targets": {"ppo_over_brax_ppo": 1.0, "training_over_raw_env": 0.6},
        "peak_rss_bytes_after_ours": rss_ours,
        "peak_rss_bytes_end": _peak_rss_bytes(),
        "wall_s": time.perf_counter() - t_start,
    }
    write_json_atomic(Path(bench["out"]), result)
    log(f"[bench] wrote {bench['out']} ({result['wall_s']:.0f} s)")
    return result


_ROW_LABELS = {
    "raw_env": "raw env (random actions)",
    "ppo": "PPO (ours)",
    "coherent_ppo": "Coherent-PPO (ours)",
    "sac": "SAC (ours)",
    "coherent_sac": "Coherent-SAC (ours)",
    "brax_ppo": "Brax PPO",
}


def format_throughput_table(result: dict) -> str:
    """The human-readable summary of `run_throughput_bench`'s result."""
    cfg = result["settings"]["config"]
    rows, ratios = result["rows"], result["ratios"]
    hidden = ",".join(map(str, cfg["policy_hidden"]))
    lines = [
        f"throughput bench: {cfg['env']}, {cfg['num_envs']} envs x {cfg['unroll_length']} steps "
        f"({result['env_steps_per_iteration']} env steps per iteration), PPO {cfg['num_epochs']} epochs x "
        f"{cfg['num_minibatches']} minibatches, policy/value [{hidden}] {cfg['activation']}",
        f"jax {result['jax_version']} on {result['device']} ({result['cpu']}, {result['cpu_count']} CPUs); "
        f"load average {result['load_average_start']} -> {result['load_average_end']}",
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
        mem = _mb(_peak(e.get("memory"))) if e.get("memory") else "-"
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
        f"{_mb(result['peak_rss_bytes_after_ours'])} MB after compiling our rows, "
        f"{_mb(result['peak_rss_bytes_end'])} MB at the end"
    )
    if "brax_ppo" in rows:
        b = rows["brax_ppo"]
        lines.append(
            f"  Brax PPO: compile = epochs' time above the steady one ({b['epoch_s'][0]:.1f} s, "
            f"{b['epoch_s'][1]:.1f} s for the first two); "
            f"setup (reset, init) {b['setup_s']:.1f} s; our rounds ran between Brax's warm epochs"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------- driver
def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str):  # numpy / jax scalars
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json_atomic(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


def run_coherent_bench(overrides: Sequence[str], log: Callable[[str], None] | None = None) -> dict:
    """Runs the ``coherent`` suite with ``key=value`` overrides; writes and returns the results.

    Raises `ConfigError` for a bad override before anything runs.
    """
    cfg, bench, _ = parse_bench_overrides(list(overrides))
    log = log or (lambda msg: print(msg, flush=True))
    import jax
    import jaxlib

    t_start = time.perf_counter()
    device = jax.devices()[0]
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    load_start = _load()
    log(
        f"[bench] coherent suite: jax {jax.__version__} on {device.platform} ({_cpu_model()}, "
        f"{os.cpu_count()} CPUs), load average {load_start}"
    )
    training, trainers = _bench_training(cfg, bench["iterations"], log)
    segment = _bench_segment_log_prob(cfg, bench, trainers, log)
    del trainers
    filt = _bench_filter(cfg, bench, log)
    result = {
        "suite": "coherent",
        "timestamp": started,
        "jax_version": jax.__version__,
        "jaxlib_version": getattr(jaxlib, "__version__", None),
        "device": str(device),
        "platform": device.platform,
        "device_kind": getattr(device, "device_kind", None),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_start": load_start,
        "load_average_end": _load(),
        "settings": {"config": to_dict(cfg), **bench},
        "training": training,
        "segment_log_prob": segment,
        "filter": filt,
        "wall_s": time.perf_counter() - t_start,
    }
    write_json_atomic(Path(bench["out"]), result)
    log(f"[bench] wrote {bench['out']} ({result['wall_s']:.0f} s)")
    return result


def format_table(result: dict) -> str:
    """The human-readable summary of `run_coherent_bench`'s result."""
    cfg = result["settings"]["config"]
    tr, seg, filt = result["training"], result["segment_log_prob"], result["filter"]
    hidden = ",".join(map(str, cfg["policy_hidden"]))
    lines = [
        f"coherent bench: {cfg['env']}, {cfg['num_envs']} envs x {cfg['unroll_length']} steps, "
        f"{cfg['algo']} {cfg['num_epochs']} epochs x {cfg['num_minibatches']} minibatches, "
        f"policy [{hidden}], beta={cfg['beta']}"
        + (f", coherent_inference={cfg['coherent_inference']}" if "coherent_inference" in cfg else ""),
        f"jax {result['jax_version']} on {result['device']} ({result['cpu']}, {result['cpu_count']} CPUs); "
        f"load average {result['load_average_start']} -> {result['load_average_end']}",
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
            f"  {label:<22}{e['compile_s']:>10.1f}{iter_s:>10}{sps:>13}{_mb(_peak(e['memory'])):>11}"
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
                f"{_mb(_peak(e['memory_grad'])):>14}{reps:>6}  {e['grad_mode']}"
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
    return "\n".join(lines)


def help_text() -> str:
    lines = [
        "usage: python -m coherent_jax.bench [SUITE] [key=value ...]",
        f"suites: {', '.join(SUITES)} (default: {DEFAULT_SUITE})",
    ]
    for suite, keys in SUITE_KEYS.items():
        lines += ["", f"{suite} suite options (key=default):"]
        for name, spec in keys.items():
            default = spec.default
            if isinstance(default, list):
                default = "[" + ",".join(map(str, default)) + "]"
            lines.append(f"  {name}={default}".ljust(34) + f"  {spec.help}")
        lines.append(
            "  and every training option of `python -m coherent_jax.train --help` except "
            + ", ".join(SET_BY_SUITE[suite])
        )
    lines += ["", "sac suite: see coherent_jax/bench_sac.py"]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(help_text())
        return 0
    if not argv or "=" in argv[0]:  # no suite named: the default one
        argv = [DEFAULT_SUITE, *argv]
    suite = argv[0]
    if suite not in SUITES:
        print(f"error: unknown suite {suite!r}; valid suites: {', '.join(SUITES)}", file=sys.stderr)
        return 2
    if argv[0] == "sac":
        from coherent_jax import bench_sac

        return bench_sac.main(argv[1:])
    try:
        parse_bench_overrides(argv[1:], suite)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if suite == "throughput":
        result = run_throughput_bench(argv[1:])
        table = format_throughput_table(result)
    else:
        result = run_coherent_bench(argv[1:])
        table = format_table(result)
    print()
    print(table, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

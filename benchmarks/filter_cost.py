"""Section 2 of the ``coherent`` suite: the block filter against the thesis's dense recursion.

`coherent_jax.exploration.coherent.filter.log_marginals` (p independent (q+1)-dimensional Kalman filters,
docs/design.md §3) against `reference.dense_log_marginals`, the recursion (4.33)-(4.49)
over the flattened p(q+1) weight vector: forward and forward+gradient times, and a
check that both give the same log-probabilities and gradients.
"""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import measure
from coherent_jax.config import Config
from coherent_jax.exploration.chain import ChainParams
from coherent_jax.exploration.coherent.filter import log_marginals
from coherent_jax.exploration.coherent.reference import dense_log_marginals, sample_segments

_FILTER_AXES = (0, 0, 0, None, None, None, None)  # batched: x, a, first; shared: the parameters


def _filter_forward(impl, chunk=0):
    """log p of every sequence of the batch (``impl`` vmapped), checkpointed every `chunk` steps if > 0."""

    def f(x, a, first, mu, w_std, action_std, beta):
        extra = {"checkpoint_chunk": chunk} if chunk else {}

        def single(x, a, first, mu, w_std, action_std, beta):
            return impl(x, a, first, ChainParams(mu, w_std, action_std, beta), **extra)

        return jax.vmap(single, _FILTER_AXES)(x, a, first, mu, w_std, action_std, beta)

    return f


def _filter_with_grad(impl, chunk=0, sequential=False):
    """value and d/d(mu, w_std) of sum log p over the batch."""

    def total(mu, w_std, x, a, first, action_std, beta):
        if sequential:  # one sequence at a time: 1/batch of the memory

            def one(inputs):
                xi, ai, fi = inputs
                logp = lambda m, s: jnp.sum(
                    impl(xi, ai, fi, ChainParams(m, s, action_std, beta), checkpoint_chunk=chunk)
                )
                return jax.value_and_grad(logp, argnums=(0, 1))(mu, w_std)

            values, (g_mu, g_std) = jax.lax.map(one, (x, a, first))
            return values.sum(), (g_mu.sum(0), g_std.sum(0))
        fwd = _filter_forward(impl, chunk)
        logp = lambda m, s: jnp.sum(fwd(x, a, first, m, s, action_std, beta))
        return jax.value_and_grad(logp, argnums=(0, 1))(mu, w_std)

    return total


def _compile_filter_grad(impl, method: str, grad_args: tuple, bench: dict, num_steps: int, log):
    """The forward+gradient program, compiled; for the dense form, checkpointed (then one
    sequence at a time) while its peak memory exceeds ``dense_mem_gb``.

    Returns (program, compile seconds, the mode used, every mode tried with its memory).
    """
    grad_mode = "vmap"
    grad, grad_compile_s = measure.compile_timed(_filter_with_grad(impl), *grad_args)
    tried = [
        {"mode": grad_mode, "peak_bytes": measure.peak(measure.memory(grad)), "compile_s": grad_compile_s}
    ]
    if method != "dense":
        return grad, grad_compile_s, grad_mode, tried
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
        log(f"[bench]   dense gradient needs {measure.mb(tried[-1]['peak_bytes'])} MB; trying {mode}")
        grad, grad_compile_s = measure.compile_timed(_filter_with_grad(impl, **kwargs), *grad_args)
        grad_mode = mode
        tried.append(
            {"mode": mode, "peak_bytes": measure.peak(measure.memory(grad)), "compile_s": grad_compile_s}
        )
    return grad, grad_compile_s, grad_mode, tried


def _bench_filter_method(q: int, method: str, inputs: tuple, grad_args: tuple, bench: dict, log):
    """One filter form (block or dense) at one q: compile, warm up, time; returns its entry and outputs."""
    log(f"[bench] filter q={q} {method}: compiling forward and forward+gradient ...")
    impl = log_marginals if method == "block" else dense_log_marginals
    fwd, fwd_compile_s = measure.compile_timed(_filter_forward(impl), *inputs)
    grad, grad_compile_s, grad_mode, tried = _compile_filter_grad(
        impl, method, grad_args, bench, bench["filter_T"], log
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
        fwd_times = measure.time_calls(fwd, inputs, repeats)
        grad_times = measure.time_calls(grad, grad_args, repeats)
    entry = {
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
        "memory_forward": measure.memory(fwd),
        "memory_grad": measure.memory(grad),
    }
    log(f"[bench]   forward {entry['forward_ms']:.2f} ms, forward+gradient {entry['grad_ms']:.2f} ms")
    return entry, (np.asarray(logp), value, [np.asarray(g) for g in grads])


def bench_filter(cfg: Config, bench: dict, log) -> dict:
    """The block filter against the dense reference, per q: agreement of log p and its
    gradient, and the forward and forward+gradient times."""
    p, num_steps, batch = bench["filter_p"], bench["filter_T"], bench["filter_batch"]
    cases = []
    for q in bench["filter_q"]:
        inputs = sample_segments(
            jax.random.PRNGKey(cfg.seed + q),
            batch,
            num_steps,
            q,
            p,
            cfg.coherent.w_std_init,
            cfg.coherent.action_std,
            cfg.coherent.beta,
        )
        x, a, first, mu, w_std, action_std, beta = inputs
        grad_args = (mu, w_std, x, a, first, action_std, beta)
        case: dict[str, Any] = {"q": q, "state_dim": p * (q + 1)}
        outputs = {}
        for method in ("block", "dense"):
            case[method], outputs[method] = _bench_filter_method(q, method, inputs, grad_args, bench, log)
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
        "beta": cfg.coherent.beta,
        "w_std": cfg.coherent.w_std_init,
        "action_std": cfg.coherent.action_std,
        "dtype": "float32",
        "dense_form": "covariance (Woodbury) form of (4.33)-(4.49), one p x p solve per step",
        "cases": cases,
    }

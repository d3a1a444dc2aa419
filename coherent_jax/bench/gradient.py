"""The ``gradient`` suite: how far each coherent loss's gradient is from the thesis's estimator.

    python -m coherent_jax.bench gradient [betas=[0,0.01,0.1,1]] [histories=[0,64,256,900]]
        [segment=64] [q=64] [p=2] [obs_size=17] [w_std=0.1] [action_std=0.1] [seed=0]
        [dtype=float64] [out=bench_results/gradient.json]

One episode of the coherent process (eqs. 4.1-4.5, 4.29) is drawn through a one-layer
tanh trunk; a segment of ``segment`` steps starts after ``history`` steps of that
episode. The loss is the A2C/PPO policy term at the collection parameters,
sum_t A_t log p(a_t | a_<t, s_<=t) over the segment with random advantages A_t. Its
gradient with respect to the trunk, mu and log w_std is compared with a float64
reference that scores the whole episode from its start through one dense joint
Gaussian (no beliefs, no blocks, no filter), for each loss form:

* ``stored`` (``coherent.gradient=stored``): the belief at the segment start computed
  at collection, held fixed in standardised coordinates and mapped onto the current
  mu and w_std;
* ``refiltered``: the episode prefix re-inferred under the current parameters
  (`coherent_exact.refiltered_marginals`), the thesis's estimator for a chain that runs
  on across segments;
* ``exact`` (``coherent.gradient=exact``, the trainer's default): the chain restarts at
  the segment start, so the process run has no history before the segment; its
  reference is the dense joint of the segment alone, and it is scored as the trainer
  scores it (`coherent_exact.chained_marginals` from the prior).

One line per (mode, beta, history) with ``cos=`` (cosine of the whole gradient),
``rel_err=`` (|g - g_ref| / |g_ref|), the two norms and the cosines of the mu and
log w_std parts. Exit status 1 if the exact or refiltered mode's cos < 0.9999 or
rel_err > 1e-4 anywhere, 2 for a bad argument.
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coherent_jax import cli
from coherent_jax.bench import measure

MODES = ("stored", "refiltered", "exact")
#: what the exact and refiltered modes must achieve against the reference
MIN_COS, MAX_REL_ERR = 0.9999, 1e-4
CHECKED = ("refiltered", "exact")


def _betas(text: str) -> list[float]:
    values = [float(v) for v in text.strip().strip("[]").split(",") if v.strip()]
    if not values or not all(0.0 <= b <= 1.0 for b in values):
        raise ValueError(text)
    return values


KEYS: dict[str, cli.Key] = {
    "betas": cli.Key([0.0, 0.01, 0.1, 1.0], _betas, "a list of numbers in [0, 1]", "chain coefficients"),
    "histories": cli.Key(
        [0, 64, 256, 900], cli.int_list(0), "a list of integers >= 0", "steps before the segment"
    ),
    "segment": cli.Key(64, cli.int_at_least(1), "an integer >= 1", "segment length T"),
    "q": cli.Key(64, cli.int_at_least(1), "an integer >= 1", "trunk width"),
    "p": cli.Key(2, cli.int_at_least(1), "an integer >= 1", "action dimensions"),
    "obs_size": cli.Key(17, cli.int_at_least(1), "an integer >= 1", "observation size"),
    "w_std": cli.Key(0.1, cli.positive_float, "a number > 0", "prior std of the last-layer weights"),
    "action_std": cli.Key(0.1, cli.positive_float, "a number > 0", "action noise std"),
    "seed": cli.Key(0, cli.int_at_least(0), "an integer >= 0", "seed of the sampled episodes"),
    "dtype": cli.Key(
        "float64", cli.choice(("float64", "float32")), "float64 or float32", "dtype of the forms"
    ),
    "out": cli.Key(
        "bench_results/gradient.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings (no training config); `ConfigError` in one line for bad input."""
    return cli.parse_command(items, KEYS, command="the gradient suite", config=False)


def sample_episode(rng, x, mu, w_std, action_std, beta):
    """Actions of one episode drawn from the chain (4.1-4.5) and (4.29), in numpy float64."""
    num_steps, p = x.shape[0], mu.shape[0]
    xh = np.concatenate([x, np.ones((num_steps, 1))], axis=1)
    w = mu + w_std * rng.normal(size=mu.shape)
    actions = np.zeros((num_steps, p))
    for t in range(num_steps):
        if t:
            w = (1 - beta) * w + beta * mu + math.sqrt(2 * beta - beta**2) * w_std * rng.normal(size=mu.shape)
        actions[t] = w @ xh[t] + action_std * rng.normal(size=p)
    return actions


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict[str, Any]:
    """Logs one line per (mode, beta, history); writes and returns the rows and whether
    the checked modes passed everywhere. float64 is on while it runs, and restored after."""
    settings = parse(items).settings
    import jax

    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", True)
    try:
        return _run(settings, log)
    finally:
        jax.config.update("jax_enable_x64", previous)


def _run(settings: dict[str, Any], log: Callable[[str], None]) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from coherent_jax.exploration import coherent as C
    from coherent_jax.exploration import coherent_exact as E

    dtype = jnp.float64 if settings["dtype"] == "float64" else jnp.float32
    p, q, seg = settings["p"], settings["q"], settings["segment"]
    log_2pi = math.log(2.0 * math.pi)

    def trunk(theta, obs):
        return jnp.tanh(obs @ theta["w"] + theta["b"])

    def heads(params):
        action_std = jnp.full((p,), settings["action_std"], params["mu"].dtype)
        return params["mu"], jnp.exp(params["log_w_std"]), action_std

    def reference_logp(params, obs, a, beta):
        """Every step's log p(a_t | a_<t, s_<=t) of one episode from its dense joint Gaussian."""
        mu, w_std, action_std = heads(params)
        x = trunk(params["theta"], obs)
        num_steps = x.shape[0]
        xh = jnp.concatenate([x, jnp.ones((num_steps, 1), x.dtype)], axis=1)
        idx = jnp.arange(num_steps)
        lag = jnp.abs(idx[:, None] - idx[None, :]).astype(x.dtype)
        decay = (1.0 - beta) ** lag
        total = jnp.zeros(num_steps, x.dtype)
        for i in range(p):
            noise = action_std[i] ** 2 * jnp.eye(num_steps, dtype=x.dtype)
            cov = decay * ((xh * w_std[i] ** 2) @ xh.T) + noise
            chol = jnp.linalg.cholesky(cov)
            r = jax.scipy.linalg.solve_triangular(chol, a[:, i] - xh @ mu[i], lower=True)
            total = total - 0.5 * (log_2pi + r**2) - jnp.log(jnp.diagonal(chol))
        return total

    @jax.jit
    def reference_grad(params, obs, a, adv, beta):
        return jax.grad(lambda prm: jnp.sum(adv * reference_logp(prm, obs, a, beta)[-seg:]))(params)

    @jax.jit
    def exact_grad(params, obs, a, adv, beta):
        def loss(prm):
            mu, w_std, action_std = heads(prm)
            x = trunk(prm["theta"], obs)
            h = x.shape[0] - seg
            first = jnp.zeros(x.shape[0], bool)
            logp, _ = E.refiltered_marginals(
                x[:h], a[:h], first[:h], x[h:], a[h:], first[h:], mu, w_std, action_std, beta
            )
            return jnp.sum(adv * logp)

        return jax.grad(loss)(params)

    @jax.jit
    def stored_grad(params, obs, a, adv, beta):
        # Collection: the belief at the segment start under the collection parameters,
        # stored in standardised coordinates and a constant of the data thereafter.
        mu0, w_std0, action_std0 = heads(params)
        x0 = trunk(params["theta"], obs)
        h = x0.shape[0] - seg
        first = jnp.zeros(x0.shape[0], bool).at[0].set(True)
        belief = C.prior_belief(mu0, w_std0)
        if h:
            _, belief, _ = E.chained_marginals(
                belief, x0[:h], a[:h], first[:h], mu0, w_std0, action_std0, beta, E.block_size(h)
            )
        z_mean = jax.lax.stop_gradient((belief.mean - mu0) / w_std0)
        z_cov = jax.lax.stop_gradient(belief.cov / (w_std0[:, :, None] * w_std0[:, None, :]))

        def loss(prm):
            mu, w_std, action_std = heads(prm)
            x = trunk(prm["theta"], obs[h:])
            start = C.Belief(mu + w_std * z_mean, w_std[:, :, None] * z_cov * w_std[:, None, :])
            logp, _, _ = C.segment_marginals_joint(start, x, a[h:], first[h:], mu, w_std, action_std, beta)
            return jnp.sum(adv * logp)

        return jax.grad(loss)(params)

    @jax.jit
    def restart_grad(params, obs, a, adv, beta):
        # The trainer's default: the chain restarts at the segment start, scored from the prior.
        def loss(prm):
            mu, w_std, action_std = heads(prm)
            h = obs.shape[0] - seg
            x = trunk(prm["theta"], obs[h:])
            first = jnp.zeros(seg, bool).at[0].set(True)
            logp, _, _ = E.chained_marginals(
                C.prior_belief(mu, w_std),
                x,
                a[h:],
                first,
                mu,
                w_std,
                action_std,
                beta,
                E.block_size(seg),
                from_prior=True,
            )
            return jnp.sum(adv * logp)

        return jax.grad(loss)(params)

    @jax.jit
    def restart_reference(params, obs, a, adv, beta):
        h = obs.shape[0] - seg
        return jax.grad(lambda prm: jnp.sum(adv * reference_logp(prm, obs[h:], a[h:], beta)))(params)

    forms = {"stored": stored_grad, "refiltered": exact_grad, "exact": restart_grad}
    flat = lambda g: np.concatenate([np.ravel(np.asarray(v, np.float64)) for v in jax.tree.leaves(g)])  # noqa: E731

    def cos(u, v):
        return float(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)))

    passed, rows = True, []
    for history in settings["histories"]:
        for beta in settings["betas"]:
            rng = np.random.default_rng([settings["seed"], history, int(beta * 1e6)])
            num_steps = history + seg
            obs = np.cumsum(rng.normal(size=(num_steps, settings["obs_size"])), axis=0) * 0.1
            theta = {
                "w": rng.normal(size=(settings["obs_size"], q)) / math.sqrt(settings["obs_size"]),
                "b": np.zeros(q),
            }
            mu = rng.normal(size=(p, q + 1)) * 0.1
            log_w_std = np.full((p, q + 1), math.log(settings["w_std"]))
            x = np.tanh(obs @ theta["w"] + theta["b"])
            a = sample_episode(rng, x, mu, settings["w_std"], settings["action_std"], beta)
            adv = rng.normal(size=seg)
            params64 = jax.tree.map(jnp.asarray, {"theta": theta, "mu": mu, "log_w_std": log_w_std})
            ref_args = (params64, jnp.asarray(obs), jnp.asarray(a), jnp.asarray(adv), beta)
            refs = {"exact": restart_reference(*ref_args)}
            args = jax.tree.map(lambda v: jnp.asarray(v, dtype), (params64, obs, a, adv))
            for mode in MODES:
                if mode not in refs:  # stored and refiltered: the whole episode's reference, once
                    refs[mode] = refs.get("episode") or reference_grad(*ref_args)
                    refs["episode"] = refs[mode]
                ref = refs[mode]
                grad = forms[mode](*args, jnp.asarray(beta, dtype))
                g, r = flat(grad), flat(ref)
                c = cos(g, r)
                rel = float(np.linalg.norm(g - r) / np.linalg.norm(r))
                ok = bool(np.isfinite(c) and np.isfinite(rel) and c >= MIN_COS and rel <= MAX_REL_ERR)
                if mode in CHECKED:
                    passed = passed and ok
                rows.append(
                    {"mode": mode, "beta": beta, "history": history, "cos": c, "rel_err": rel, "ok": ok}
                )
                log(
                    f"mode={mode:6s} beta={beta:<5g} history={history:<4d} cos={c:.6f} rel_err={rel:.3e} "
                    f"norm={np.linalg.norm(g):.4g} norm_ref={np.linalg.norm(r):.4g} "
                    f"cos_mu={cos(flat(grad['mu']), flat(ref['mu'])):.4f} "
                    f"cos_log_w_std={cos(flat(grad['log_w_std']), flat(ref['log_w_std'])):.4f}"
                    + ("" if mode not in CHECKED else ("  ok" if ok else "  FAIL"))
                )
    result = {
        "suite": "gradient",
        "settings": settings,
        "rows": rows,
        "passed": passed,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    measure.write_json_atomic(Path(settings["out"]), result)
    log(f"wrote {settings['out']}")
    return result


def format_table(result: dict[str, Any]) -> str:
    """One line per (mode, beta, history), and the verdict."""
    lines = [f"  {'mode':<11}{'beta':>6}{'history':>9}{'cos':>11}{'rel_err':>11}"]
    for r in result["rows"]:
        lines.append(
            f"  {r['mode']:<11}{r['beta']:>6g}{r['history']:>9}{r['cos']:>11.6f}{r['rel_err']:>11.2e}"
            + ("" if r["mode"] not in CHECKED else ("  ok" if r["ok"] else "  FAIL"))
        )
    verdict = "passed" if result["passed"] else "FAILED"
    lines.append(
        f"  {', '.join(CHECKED)}: {verdict} (cos >= {MIN_COS}, rel_err <= {MAX_REL_ERR:g} everywhere)"
    )
    return "\n".join(lines)


def exit_status(result: dict[str, Any]) -> int:
    """1 when a checked mode missed its bound anywhere."""
    return 0 if result["passed"] else 1

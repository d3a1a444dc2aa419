"""Gradient bench: how far each coherent loss's gradient is from the thesis's estimator.

``python -m coherent_jax.bench_gradient [key=value ...]`` (``python -m coherent_jax.bench
gradient`` once it joins the bench package). One episode of the coherent process
(eqs. 4.1-4.5, 4.29) is drawn through a one-layer tanh trunk; a segment of ``segment``
steps starts after ``history`` steps of that episode. The loss is the A2C/PPO policy
term at the collection parameters, sum_t A_t log p(a_t | a_<t, s_<=t) over the
segment with random advantages A_t. Its gradient with respect to the trunk, mu and
log w_std is compared with a float64 reference that scores the whole episode from
its start through one dense joint Gaussian (no beliefs, no blocks, no filter), for
each loss form:

* ``stored`` (``coherent.gradient=stored``): the belief at the segment start computed
  at collection, held fixed in standardised coordinates and mapped onto the current
  mu and w_std (`CoherentExploration.log_prob`);
* ``exact``: the episode prefix re-inferred under the current parameters
  (`coherent_exact.refiltered_marginals`), the thesis's estimator.

One line per (mode, beta, history) with ``cos=`` (cosine of the whole gradient),
``rel_err=`` (|g - g_ref| / |g_ref|), the two norms and the cosines of the mu and
log w_std parts. Exit status 1 if the exact mode's cos < 0.9999 or rel_err > 1e-4
anywhere, 2 for a bad argument.

Keys: ``betas`` and ``histories`` (comma-separated), ``segment`` (64), ``q`` (64),
``p`` (2), ``obs_size`` (17), ``w_std`` (0.1), ``action_std`` (0.1), ``seed`` (0),
``dtype`` (float64, the estimator's own error; float32 adds rounding).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

DEFAULTS = {
    "betas": "0,0.01,0.1,1",
    "histories": "0,64,256,900",
    "segment": "64",
    "q": "64",
    "p": "2",
    "obs_size": "17",
    "w_std": "0.1",
    "action_std": "0.1",
    "seed": "0",
    "dtype": "float64",
}
MODES = ("stored", "exact")
#: what the exact mode must achieve against the reference
MIN_COS, MAX_REL_ERR = 0.9999, 1e-4


class Settings(NamedTuple):
    betas: tuple[float, ...]
    histories: tuple[int, ...]
    segment: int
    q: int
    p: int
    obs_size: int
    w_std: float
    action_std: float
    seed: int
    dtype: str


def parse(argv: Sequence[str]) -> Settings:
    """key=value arguments over `DEFAULTS`; ValueError names a bad one."""
    values = dict(DEFAULTS)
    for item in argv:
        key, sep, value = item.partition("=")
        if not sep or key not in DEFAULTS:
            raise ValueError(f"unknown argument {item!r}; keys: {', '.join(DEFAULTS)}")
        values[key] = value
    settings = Settings(
        betas=tuple(float(b) for b in values["betas"].split(",")),
        histories=tuple(int(h) for h in values["histories"].split(",")),
        segment=int(values["segment"]),
        q=int(values["q"]),
        p=int(values["p"]),
        obs_size=int(values["obs_size"]),
        w_std=float(values["w_std"]),
        action_std=float(values["action_std"]),
        seed=int(values["seed"]),
        dtype=values["dtype"],
    )
    if not all(0.0 <= b <= 1.0 for b in settings.betas):
        raise ValueError(f"betas must lie in [0, 1], got {settings.betas}")
    if min(settings.histories) < 0 or min(settings.segment, settings.q, settings.p, settings.obs_size) < 1:
        raise ValueError("histories >= 0 and segment, q, p, obs_size >= 1")
    if settings.dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be float32 or float64, got {settings.dtype!r}")
    return settings


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


def run(settings: Settings, out=print) -> bool:
    """Prints one line per (mode, beta, history); True if the exact mode passes everywhere."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from coherent_jax.exploration import coherent as C
    from coherent_jax.exploration import coherent_exact as E

    dtype = jnp.float64 if settings.dtype == "float64" else jnp.float32
    p, q, seg = settings.p, settings.q, settings.segment
    log_2pi = math.log(2.0 * math.pi)

    def trunk(theta, obs):
        return jnp.tanh(obs @ theta["w"] + theta["b"])

    def heads(params):
        action_std = jnp.full((p,), settings.action_std, params["mu"].dtype)
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

    forms = {"stored": stored_grad, "exact": exact_grad}
    flat = lambda g: np.concatenate([np.ravel(np.asarray(v, np.float64)) for v in jax.tree.leaves(g)])  # noqa: E731

    def cos(u, v):
        return float(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)))

    passed = True
    for history in settings.histories:
        for beta in settings.betas:
            rng = np.random.default_rng([settings.seed, history, int(beta * 1e6)])
            num_steps = history + seg
            obs = np.cumsum(rng.normal(size=(num_steps, settings.obs_size)), axis=0) * 0.1
            theta = {
                "w": rng.normal(size=(settings.obs_size, q)) / math.sqrt(settings.obs_size),
                "b": np.zeros(q),
            }
            mu = rng.normal(size=(p, q + 1)) * 0.1
            log_w_std = np.full((p, q + 1), math.log(settings.w_std))
            x = np.tanh(obs @ theta["w"] + theta["b"])
            a = sample_episode(rng, x, mu, settings.w_std, settings.action_std, beta)
            adv = rng.normal(size=seg)
            params64 = jax.tree.map(jnp.asarray, {"theta": theta, "mu": mu, "log_w_std": log_w_std})
            ref = reference_grad(params64, jnp.asarray(obs), jnp.asarray(a), jnp.asarray(adv), beta)
            args = jax.tree.map(lambda v: jnp.asarray(v, dtype), (params64, obs, a, adv))
            for mode in MODES:
                grad = forms[mode](*args, jnp.asarray(beta, dtype))
                g, r = flat(grad), flat(ref)
                c = cos(g, r)
                rel = float(np.linalg.norm(g - r) / np.linalg.norm(r))
                ok = bool(np.isfinite(c) and np.isfinite(rel) and c >= MIN_COS and rel <= MAX_REL_ERR)
                if mode == "exact":
                    passed = passed and ok
                out(
                    f"mode={mode:6s} beta={beta:<5g} history={history:<4d} cos={c:.6f} rel_err={rel:.3e} "
                    f"norm={np.linalg.norm(g):.4g} norm_ref={np.linalg.norm(r):.4g} "
                    f"cos_mu={cos(flat(grad['mu']), flat(ref['mu'])):.4f} "
                    f"cos_log_w_std={cos(flat(grad['log_w_std']), flat(ref['log_w_std'])):.4f}"
                    + ("" if mode != "exact" else ("  ok" if ok else "  FAIL"))
                )
    return passed


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(__doc__)
        return 0
    try:
        settings = parse(argv)
    except ValueError as err:
        print(f"bench gradient: {err}", file=sys.stderr)
        return 2
    return 0 if run(settings) else 1


if __name__ == "__main__":
    sys.exit(main())

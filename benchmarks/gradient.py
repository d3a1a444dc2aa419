"""The ``gradient`` suite: how far each coherent loss's gradient is from the thesis's estimator.

    python -m benchmarks gradient [betas=[0,0.01,0.1,1]] [histories=[0,64,256,900]]
        [segment=64] [q=64] [p=2] [obs_size=17] [w_std=0.1] [action_std=0.1] [seed=0]
        [dtype=float64] [out=bench_results/gradient.json]

One episode of the coherent process (eqs. 4.1-4.5, 4.29) is drawn through a one-layer
tanh trunk at the collection parameters; a segment of ``segment`` steps starts after
``history`` steps of that episode. The loss is the A2C/PPO policy term
sum_t A_t log p(a_t | ...) over the segment with random advantages A_t, evaluated at
parameters moved away from the collection parameters (each by ``move`` times a standard
normal), as after an update. Each mode's segment log-probabilities and the gradient of
the loss (trunk, mu and log w_std) are compared, in float64 by default, with two dense
references (one joint Gaussian, no beliefs, no blocks, no filter):

* ``episode``: one chain through the whole episode from its first step;
* ``segment``: the chain restarted at the segment's first step.

The modes, as the trainer runs them:

* ``exact`` (``coherent.gradient=exact``, the default): the segment scored from the prior;
  exact for the ``segment`` reference (the process whose chain is cut at every segment);
* ``episode`` (``coherent.gradient=episode``): the strategy's `log_prob` of the window of
  prefix and segment that the trainer hands its loss (for episodes of the longest history
  and a segment, padded in front: a shorter history's window skips its padded blocks, as
  the trainer skips those before an episode's start); exact for the ``episode`` reference;
* ``stored`` (``coherent.gradient=stored``): the belief at the segment start inferred at
  collection, held fixed in standardised coordinates and mapped onto the current mu and
  w_std; exact for neither once the segment has a history.

One line per (mode, beta, history) with ``cos`` (cosine of the whole gradient) and
``rel_err`` (|g - g_ref| / |g_ref|) against each reference; the JSON also has the largest
log-probability error. Exit status 1 if a mode misses cos >= 0.9999 or rel_err <= 1e-4
against the reference it must equal (`MUST_EQUAL`) anywhere, 2 for a bad argument.
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import measure
from coherent_jax.config import cli
from coherent_jax.exploration.base import Segment
from coherent_jax.exploration.chain import ChainParams, chain_params
from coherent_jax.exploration.coherent import exact as E
from coherent_jax.exploration.coherent import filter as F
from coherent_jax.exploration.coherent import joint as J
from coherent_jax.exploration.coherent import strategy as C
from coherent_jax.exploration.coherent.layer import CoherentHParams

MODES = ("stored", "exact", "episode")
#: which reference each mode is exact for: ``episode`` the whole-episode chain, ``segment``
#: the chain restarted at the segment's first step; ``stored`` is exact for neither
MUST_EQUAL = {"exact": "segment", "episode": "episode"}
#: what a mode must achieve against its reference
MIN_COS, MAX_REL_ERR = 0.9999, 1e-4


def _betas(text: str) -> list[float]:
    values = [float(v) for v in text.strip().strip("[]").split(",") if v.strip()]
    if not values or not all(0.0 <= b <= 1.0 for b in values):
        raise ValueError(text)
    return values


# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~100 s (97 s measured)"
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
    "move": cli.Key(
        0.05,
        cli.positive_float,
        "a number > 0",
        "std of the random move from the collection parameters to where the gradients are taken",
    ),
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


def sample_episode(rng, x, params: ChainParams):
    """Actions of one episode drawn from the chain (4.1-4.5) and (4.29), in numpy float64."""
    mu, w_std, action_std, beta = params
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
    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", True)
    try:
        return _run(settings, log)
    finally:
        jax.config.update("jax_enable_x64", previous)


class _Forms:
    """The loss's log p of a segment in each mode, and the two dense references, as functions of
    ``(params, obs, a, beta, params0)`` for the settings' ``p``, ``q`` and ``segment``."""

    def __init__(self, settings: dict[str, Any]) -> None:
        self.settings = settings
        self.p, self.q, self.seg = settings["p"], settings["q"], settings["segment"]
        # The trainer's coherent strategy in episode mode, for episodes of the longest history
        # and a segment: every case's window has that episode's length, as a trainer's windows
        # do, and the blocks before a shorter episode's start are skipped as there.
        self.strategy = C.CoherentExploration(
            self.p, [self.q], "tanh", 0.0, settings["w_std"], settings["action_std"],
            gradient="episode", episode_length=max(settings["histories"]) + self.seg,
            unroll_length=self.seg,
        )  # fmt: skip

    def trunk(self, params, obs):
        return self.strategy.layer.features(params, obs)

    def heads(self, params):
        action_std = jnp.full((self.p,), self.settings["action_std"], params["mu"].dtype)
        return params["mu"], jnp.exp(params["log_w_std"]), action_std

    def reference_logp(self, params, obs, a, beta):
        """Every step's log p(a_t | a_<t, s_<=t) of one chain from the first step of ``obs``,
        from its dense joint Gaussian (no beliefs, no blocks, no filter)."""
        log_2pi = math.log(2.0 * math.pi)
        mu, w_std, action_std = self.heads(params)
        x = self.trunk(params, obs)
        num_steps = x.shape[0]
        xh = jnp.concatenate([x, jnp.ones((num_steps, 1), x.dtype)], axis=1)
        idx = jnp.arange(num_steps)
        decay = (1.0 - beta) ** jnp.abs(idx[:, None] - idx[None, :]).astype(x.dtype)
        total = jnp.zeros(num_steps, x.dtype)
        for i in range(self.p):
            cov = decay * ((xh * w_std[i] ** 2) @ xh.T) + action_std[i] ** 2 * jnp.eye(
                num_steps, dtype=x.dtype
            )
            chol = jnp.linalg.cholesky(cov)
            r = jax.scipy.linalg.solve_triangular(chol, a[:, i] - xh @ mu[i], lower=True)
            total = total - 0.5 * (log_2pi + r**2) - jnp.log(jnp.diagonal(chol))
        return total

    # The two processes a mode can be exact for: one chain through the whole episode, or
    # a chain restarted at the segment's first step. Each gives (logp, loss) of the segment.
    def whole_episode(self, params, obs, a, beta, params0):
        return self.reference_logp(params, obs, a, beta)[-self.seg :]

    def restarted(self, params, obs, a, beta, params0):
        return self.reference_logp(params, obs[-self.seg :], a[-self.seg :], beta)

    def episode_mode(self, params, obs, a, beta, params0):
        """``coherent.gradient=episode`` as the trainer's loss runs it: the strategy's
        `log_prob` of the window of `history_length` prefix steps (padded in front as
        the trainer's empty history is) and the segment; the last T steps."""
        del params0
        p, seg = self.p, self.seg
        strat = self.strategy
        pad = strat.history_length + seg - obs.shape[0]
        first = jnp.concatenate([jnp.ones(pad, bool), jnp.zeros(obs.shape[0], bool)])
        w_obs = jnp.concatenate([jnp.zeros((pad, obs.shape[1]), obs.dtype), obs])
        w_a = jnp.concatenate([jnp.zeros((pad, p), a.dtype), a])
        hp = CoherentHParams(action_std=self.heads(params)[2], beta=beta)
        return strat.log_prob(params, hp, Segment(w_obs, w_a, first.at[pad].set(True))).log_prob[-seg:]

    def exact_mode(self, params, obs, a, beta, params0):
        """``coherent.gradient=exact``: the segment scored from the prior, as the trainer does."""
        del params0
        seg = self.seg
        mu, w_std, action_std = self.heads(params)
        x = self.trunk(params, obs[-seg:])
        first = jnp.zeros(seg, bool).at[0].set(True)
        prior = F.prior_belief(mu, w_std)
        chain = chain_params(mu, w_std, action_std, beta)
        logp, _, _ = E.chained_marginals(prior, x, a[-seg:], first, chain, E.block_size(seg), from_prior=True)
        return logp

    def stored_mode(self, params, obs, a, beta, params0):
        """``coherent.gradient=stored``: the belief at the segment start inferred at collection
        (``params0``), held in standardised coordinates and mapped onto ``params``."""
        mu0, w_std0, action_std0 = self.heads(params0)
        h = obs.shape[0] - self.seg
        belief = F.prior_belief(mu0, w_std0)
        if h:
            first = jnp.zeros(h, bool).at[0].set(True)
            x0 = self.trunk(params0, obs[:h])
            chain0 = chain_params(mu0, w_std0, action_std0, beta)
            _, belief, _ = E.chained_marginals(belief, x0, a[:h], first, chain0, E.block_size(h))
        z_mean = jax.lax.stop_gradient((belief.mean - mu0) / w_std0)
        z_cov = jax.lax.stop_gradient(belief.cov / (w_std0[:, :, None] * w_std0[:, None, :]))
        mu, w_std, action_std = self.heads(params)
        start = F.Belief(mu + w_std * z_mean, w_std[:, :, None] * z_cov * w_std[:, None, :])
        first = jnp.zeros(self.seg, bool).at[0].set(h == 0)
        chain = chain_params(mu, w_std, action_std, beta)
        logp, _, _ = J.segment_marginals_joint(start, self.trunk(params, obs[h:]), a[h:], first, chain)
        return logp


def _value_and_grad(fn):
    """``fn``'s log p and the gradient of the advantage-weighted loss ``sum(adv * log p)``, jitted."""

    def loss(params, obs, a, adv, beta, params0):
        return jnp.sum(adv * fn(params, obs, a, beta, params0))

    @jax.jit
    def run(params, obs, a, adv, beta, params0):
        logp = fn(params, obs, a, beta, params0)
        return logp, jax.grad(loss)(params, obs, a, adv, beta, params0)

    return run


def _case(settings: dict[str, Any], forms: _Forms, history: int, beta: float):
    """One (history, beta) case in float64: the collection parameters, the parameters after a
    move (as after an update), the observations, an episode sampled from the process, advantages."""
    p, q, seg = forms.p, forms.q, forms.seg
    rng = np.random.default_rng([settings["seed"], history, int(beta * 1e6)])
    num_steps = history + seg
    obs = np.cumsum(rng.normal(size=(num_steps, settings["obs_size"])), axis=0) * 0.1
    init = forms.strategy.init(jax.random.PRNGKey(settings["seed"]), settings["obs_size"])
    params0 = {
        "trunk": jax.tree.map(lambda v: np.asarray(v, np.float64), init["trunk"]),
        "mu": rng.normal(size=(p, q + 1)) * 0.1,
        "log_w_std": np.full((p, q + 1), math.log(settings["w_std"])),
    }
    x = np.asarray(forms.trunk(jax.tree.map(jnp.asarray, params0), jnp.asarray(obs)))
    a = sample_episode(rng, x, ChainParams(params0["mu"], settings["w_std"], settings["action_std"], beta))
    adv = rng.normal(size=seg)
    # Evaluated away from the collection parameters, as after an update.
    params = jax.tree.map(lambda v, r=rng: v + settings["move"] * r.normal(size=np.shape(v)), params0)
    return params, obs, a, adv, params0


def _flat(g) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(v, np.float64)) for v in jax.tree.leaves(g)])


def _cos(u, v) -> float:
    return float(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)))


def _compare(mode: str, beta: float, history: int, logp, grad, ref_out: dict) -> dict[str, Any]:
    """A mode's row: cosine, relative error and value error against each reference; whether
    it equals the one it must equal (`MUST_EQUAL`) within `MIN_COS` and `MAX_REL_ERR`."""
    row = {"mode": mode, "beta": beta, "history": history, "must_equal": MUST_EQUAL.get(mode)}
    for name, (ref_logp, ref_grad) in ref_out.items():
        g, r = _flat(grad), _flat(ref_grad)
        row[f"cos_{name}"] = _cos(g, r)
        row[f"rel_err_{name}"] = float(np.linalg.norm(g - r) / np.linalg.norm(r))
        row[f"value_err_{name}"] = float(np.max(np.abs(np.asarray(logp, np.float64) - ref_logp)))
    ok = True
    if mode in MUST_EQUAL:
        ref = MUST_EQUAL[mode]
        c, rel = row[f"cos_{ref}"], row[f"rel_err_{ref}"]
        ok = bool(np.isfinite(c) and np.isfinite(rel) and c >= MIN_COS and rel <= MAX_REL_ERR)
    row["ok"] = ok
    return row


def _run(settings: dict[str, Any], log: Callable[[str], None]) -> dict[str, Any]:
    """Every (history, beta, mode): the mode's gradient (in ``dtype``) against the float64
    references; writes the JSON and returns it (``passed``: every must-equal row held)."""
    dtype = jnp.float64 if settings["dtype"] == "float64" else jnp.float32
    forms = _Forms(settings)
    modes = {
        m: _value_and_grad(f)
        for m, f in zip(MODES, (forms.stored_mode, forms.exact_mode, forms.episode_mode), strict=True)
    }
    refs = {"episode": _value_and_grad(forms.whole_episode), "segment": _value_and_grad(forms.restarted)}
    passed, rows = True, []
    for history in settings["histories"]:
        for beta in settings["betas"]:
            params, obs, a, adv, params0 = _case(settings, forms, history, beta)
            args64 = jax.tree.map(jnp.asarray, (params, obs, a, adv))
            ref_out = {k: f(*args64, beta, jax.tree.map(jnp.asarray, params0)) for k, f in refs.items()}
            args = jax.tree.map(lambda v: jnp.asarray(v, dtype), (params, obs, a, adv, params0))
            for mode in MODES:
                logp, grad = modes[mode](*args[:4], jnp.asarray(beta, dtype), args[4])
                row = _compare(mode, beta, history, logp, grad, ref_out)
                passed = passed and row["ok"]
                rows.append(row)
                log(
                    f"mode={mode:7s} beta={beta:<5g} history={history:<4d} "
                    f"episode: cos={row['cos_episode']:.6f} rel_err={row['rel_err_episode']:.2e}  "
                    f"segment: cos={row['cos_segment']:.6f} rel_err={row['rel_err_segment']:.2e}"
                    + (
                        ""
                        if mode not in MUST_EQUAL
                        else f"  must equal {MUST_EQUAL[mode]}: {'ok' if row['ok'] else 'FAIL'}"
                    )
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
    """One line per (mode, beta, history) against both references, and the verdict."""
    lines = [
        f"  {'mode':<9}{'beta':>6}{'history':>8}{'cos(episode)':>14}{'rel(episode)':>13}"
        f"{'cos(segment)':>14}{'rel(segment)':>13}  must equal"
    ]
    for r in result["rows"]:
        must = r.get("must_equal")
        lines.append(
            f"  {r['mode']:<9}{r['beta']:>6g}{r['history']:>8}"
            f"{r['cos_episode']:>14.6f}{r['rel_err_episode']:>13.2e}"
            f"{r['cos_segment']:>14.6f}{r['rel_err_segment']:>13.2e}  "
            + ("-" if must is None else f"{must}: {'ok' if r['ok'] else 'FAIL'}")
        )
    verdict = "passed" if result["passed"] else "FAILED"
    checked = ", ".join(f"{m} = {ref}" for m, ref in MUST_EQUAL.items())
    lines.append(f"  {checked}: {verdict} (cos >= {MIN_COS}, rel_err <= {MAX_REL_ERR:g} everywhere)")
    return "\n".join(lines)


def exit_status(result: dict[str, Any]) -> int:
    """1 when a checked mode missed its bound anywhere."""
    return 0 if result["passed"] else 1

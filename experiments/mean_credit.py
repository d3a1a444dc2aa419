"""How much gradient each step of a long chain gives the policy's mean weights.

    PYTHONPATH=. python experiments/mean_credit.py [OUT.json] [--steps 1000] [--betas 0,0.01,0.1,1]
                                                  [--episodes 3] [--seed 0]

The on-policy loss weights every step's marginal score d log p(a_t | a_<t, s_<=t) / d mu
(eqs. 4.37 and 4.49) by its advantage. Along one chain of T steps this prints the root
mean square of that score per window of steps, for each beta, in float64, with actions
drawn from the chain itself (eqs. 4.1-4.5 and 4.29). The last-layer inputs are a smooth
synthetic stand-in for a trunk's features (q = 64 tanh units of an AR(1) process with
coefficient 0.95), and the parameters are the protocol's initial ones (w_std 0.1,
action_std 0.1, p = 6, mu ~ N(0, 0.01^2)).

At beta = 0 the chain is one draw of w for the episode: the sum of the scores is
Lambda (E[w | a_0:T] - mu), so once the actions have pinned w down the later steps add
little. At beta = 1 each step's score is that of its own Gaussian and stays level. The
figures go to OUT.json (default bench_results/mean_credit.json).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.gradient import sample_episode
from benchmarks.measure import write_json_atomic
from coherent_jax.exploration.chain import ChainParams
from coherent_jax.exploration.coherent.filter import log_marginals

#: the windows of steps the table reports, as [start, end) (end clipped to T)
WINDOWS = ((0, 1), (1, 10), (10, 65), (65, 200), (200, 1000))


def smooth_features(rng: np.random.Generator, num_steps: int, q: int, rho: float = 0.95) -> np.ndarray:
    """[T, q] tanh of a stationary AR(1) process with coefficient ``rho``."""
    z, out = rng.normal(size=q), np.empty((num_steps, q))
    for t in range(num_steps):
        if t:
            z = rho * z + math.sqrt(1 - rho**2) * rng.normal(size=q)
        out[t] = np.tanh(z)
    return out


def step_scores(x, a, params: ChainParams) -> np.ndarray:
    """[T, p, q+1]: d log p(a_t | a_<t, s_<=t) / d mu for every t of one episode (call under x64)."""
    first = jnp.zeros(x.shape[0], bool).at[0].set(True)
    fn = lambda m: log_marginals(x, a, first, params._replace(mu=m))  # noqa: E731
    return np.asarray(jax.jacfwd(fn)(jnp.asarray(params.mu)))


def credit(num_steps: int, betas: list[float], episodes: int, seed: int, p: int = 6, q: int = 64) -> dict:
    """Per beta, the rms score per window and the share of the summed squares in the first 65 steps."""
    rng = np.random.default_rng(seed)
    x = smooth_features(rng, num_steps, q)
    mu = 0.01 * rng.normal(size=(p, q + 1))
    w_std, action_std = np.full((p, q + 1), 0.1), np.full(p, 0.1)
    windows = [(a, min(b, num_steps)) for a, b in WINDOWS if a < num_steps]
    rows = []
    for beta in betas:
        sq = np.zeros(num_steps)
        for _ in range(episodes):
            params = ChainParams(mu, w_std, action_std, beta)
            a = sample_episode(rng, x, params)
            sq += np.sum(step_scores(x, a, params) ** 2, axis=(1, 2)) / episodes
        rows.append(
            {
                "beta": beta,
                "rms_by_window": {f"[{a},{b})": float(np.sqrt(sq[a:b].mean())) for a, b in windows},
                "share_first_65": float(sq[:65].sum() / sq.sum()),
            }
        )
    return {"steps": num_steps, "episodes": episodes, "seed": seed, "p": p, "q": q, "rows": rows}


def _betas(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        message = f"invalid betas {text!r}: expected numbers in [0, 1], e.g. 0,0.01,1"
        raise argparse.ArgumentTypeError(message) from None
    if not values or any(not 0.0 <= v <= 1.0 for v in values):
        raise argparse.ArgumentTypeError(f"invalid betas {text!r}: each must be in [0, 1]")
    return values


def _positive(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: expected an integer >= 1")
    return int(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="bench_results/mean_credit.json")
    parser.add_argument("--steps", type=_positive, default=1000)
    parser.add_argument("--betas", type=_betas, default=[0.0, 0.01, 0.1, 1.0])
    parser.add_argument("--episodes", type=_positive, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with jax.enable_x64(True):
        result = credit(args.steps, args.betas, args.episodes, args.seed)
    for row in result["rows"]:
        cells = "  ".join(f"{w} {v:6.2f}" for w, v in row["rms_by_window"].items())
        share = row["share_first_65"]
        print(f"beta {row['beta']:<5}  rms score by steps: {cells}  share in the first 65: {share:.3f}")
    out = Path(args.out)
    write_json_atomic(out, result)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""experiments/mean_credit.py: the per-step scores of the mean against closed forms in float64.

References: the chain (4.1)-(4.5) with w integrated out makes each action dimension's
actions of an episode one Gaussian, a_i ~ N(X mu_i, C_i) with
C_i[s, t] = (1 - beta)^|s - t| x_s' diag(w_std_i^2) x_t + action_std_i^2 [s = t]
(x with a trailing 1 for the bias). The scores of every step sum to the gradient of
its log-density, X' C_i^-1 (a_i - X mu_i); at beta = 1 each step is its own Gaussian.
"""

import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT, child_env, load_experiment

from coherent_jax.exploration.chain import ChainParams

credit = load_experiment("mean_credit")


def _problem(beta, seed=0, num_steps=30, p=2, q=4):
    rng = np.random.default_rng(seed)
    x = credit.smooth_features(rng, num_steps, q)
    mu = 0.3 * rng.normal(size=(p, q + 1))
    w_std = rng.uniform(0.2, 0.6, size=(p, q + 1))
    action_std = rng.uniform(0.1, 0.3, size=p)
    a = credit.sample_episode(rng, x, ChainParams(mu, w_std, action_std, beta))
    return x, a, mu, w_std, action_std


@pytest.mark.parametrize("beta", [0.0, 0.05, 0.3])
def test_the_scores_of_an_episode_sum_to_the_gradient_of_its_joint_density(beta, x64):
    x, a, mu, w_std, action_std = _problem(beta)
    scores = credit.step_scores(x, a, ChainParams(mu, w_std, action_std, beta))
    xh = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    lag = np.abs(np.subtract.outer(np.arange(len(x)), np.arange(len(x))))
    for i in range(mu.shape[0]):
        cov = (1 - beta) ** lag * ((xh * w_std[i] ** 2) @ xh.T) + action_std[i] ** 2 * np.eye(len(x))
        expected = xh.T @ np.linalg.solve(cov, a[:, i] - xh @ mu[i])
        np.testing.assert_allclose(scores[:, i].sum(0), expected, rtol=1e-9, atol=1e-9)


def test_at_beta_one_each_steps_score_is_that_of_its_own_gaussian(x64):
    x, a, mu, w_std, action_std = _problem(1.0, seed=1)
    scores = credit.step_scores(x, a, ChainParams(mu, w_std, action_std, 1.0))
    xh = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    var = (xh**2) @ (w_std**2).T + action_std**2  # [T, p]
    expected = ((a - xh @ mu.T) / var)[:, :, None] * xh[:, None, :]
    np.testing.assert_allclose(scores, expected, rtol=1e-9, atol=1e-12)


def test_the_table_has_one_row_per_beta_and_its_windows_clipped_to_the_episode(x64):
    out = credit.credit(70, [0.0, 1.0], episodes=1, seed=0, p=2, q=4)
    assert [r["beta"] for r in out["rows"]] == [0.0, 1.0]
    for row in out["rows"]:
        assert list(row["rms_by_window"]) == ["[0,1)", "[1,10)", "[10,65)", "[65,70)"]
        assert 0.0 < row["share_first_65"] < 1.0


def test_bad_betas_exit_2_naming_the_value_and_write_nothing(tmp_path):
    out = tmp_path / "credit.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "mean_credit.py"), str(out), "--betas", "0,2"],
        capture_output=True,
        text=True,
        env=child_env(),
        timeout=120,
    )
    assert proc.returncode == 2
    assert "invalid betas '0,2'" in proc.stderr and "[0, 1]" in proc.stderr
    assert not out.exists()

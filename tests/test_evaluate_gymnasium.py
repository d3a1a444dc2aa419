"""``python -m coherent_jax.evaluate RUN_DIR engine=gymnasium``: a policy trained here, run in
``gymnasium.make(...)`` itself, returns what it returns in our engine; the refusals."""

import json
import sys

import numpy as np
import pytest
from test_evaluate import POINTMASS, make_fake_run

from coherent_jax.evaluate import main, parse_eval_args

# PPO on Gymnasium's InvertedPendulum-v5 for 8 iterations of 1,024 env steps: a policy
# that balances the pole for about 80 steps (an untrained one: about 25).
PENDULUM = [
    "env=inverted_pendulum",
    "num_envs=32",
    "unroll_length=32",
    "num_minibatches=4",
    "total_steps=8192",
    "eval_every=100",
    "episode_length=200",
    "progress=false",
]


@pytest.mark.slow
def test_trained_policy_returns_the_same_in_gymnasium(tmp_path, capsys):
    """Gymnasium's mean return lies within the episodes' spread of ours.

    The two engines' initial states are different draws from the same distribution, so
    the means differ by sampling error only: the tolerance is the pooled standard
    deviation of the episodes' returns (about 2.8 standard errors of the difference of
    two 16-episode means), at least one step. Measured with this policy (ours 80.5 +- 2.0,
    Gymnasium 79.4 +- 1.9): Gymnasium's mean falls to 69.5 when the action is passed on
    without mapping [-1, 1] onto the action bounds [-3, 3], to 74.3 with half of that map,
    to 46.0 when the observations are not normalised and to 4.5 with the action negated,
    each far outside the tolerance.
    """
    from coherent_jax.train import main as train

    run = tmp_path / "run"
    assert train([*PENDULUM, f"run_dir={run}"]) == 0
    capsys.readouterr()
    assert main([str(run), "episodes=16", "engine=gymnasium", "seed=1"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    result = json.loads(out[-1])
    assert result["engine"] == "gymnasium" and result["gymnasium_id"] == "InvertedPendulum-v5"
    assert "Gymnasium" in out[-2] and "InvertedPendulum-v5" in out[-2] and "+-" in out[-2]
    ours, theirs = result["return_mean"], result["gymnasium_return_mean"]
    print(
        f"ours {ours:.2f} +- {result['return_std']:.2f}, Gymnasium {theirs:.2f} +- "
        f"{result['gymnasium_return_std']:.2f}"
    )
    assert ours > 40.0, f"the policy did not learn to balance: {result}"
    spread = np.sqrt((result["return_std"] ** 2 + result["gymnasium_return_std"] ** 2) / 2)
    assert abs(theirs - ours) <= max(spread, 1.0), result
    # InvertedPendulum-v5 pays 1 for every step but the falling one.
    assert result["gymnasium_episode_length_mean"] - 1 <= theirs <= result["gymnasium_episode_length_mean"]
    # seed= draws the Gymnasium episodes: the same seed repeats them.
    assert main([str(run), "episodes=16", "engine=gymnasium", "seed=1"]) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (
        again["gymnasium_return_mean"] == theirs
        and again["gymnasium_return_std"] == result["gymnasium_return_std"]
    )


@pytest.mark.parametrize("env", ["pointmass", "brax-hopper", "dmc-cartpole_balance"])
def test_task_without_gymnasium_id_is_refused(tmp_path, capsys, env):
    overrides = [f"env={env}", *POINTMASS[1:]]
    run = make_fake_run(tmp_path / "run", overrides)
    before = sorted(p.name for p in run.rglob("*"))
    assert main([str(run), "engine=gymnasium"]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and f"env={env}" in err[0], err
    assert "halfcheetah" in err[0] and "InvertedPendulum-v5" in err[0] and "'engine'" in err[0]
    assert "evaluating" not in captured.out
    assert sorted(p.name for p in run.rglob("*")) == before


def test_gymnasium_missing_names_the_extra(tmp_path, capsys, monkeypatch):
    """Without gymnasium[mujoco] importable, one line says which extra to install."""
    run = make_fake_run(tmp_path / "run", ["env=halfcheetah", *POINTMASS[1:]])
    monkeypatch.setitem(sys.modules, "gymnasium.envs.mujoco.mujoco_env", None)
    assert main([str(run), "engine=gymnasium"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gymnasium[mujoco]" in err[0] and '".[gym]"' in err[0], err


@pytest.mark.parametrize(
    "args,text",
    [(["engine=mujoco"], "'engine'.*jax or gymnasium"), (["engine=gymnasium", "video=true"], "'engine'")],
)
def test_bad_engine_is_refused(tmp_path, args, text):
    from coherent_jax.config import ConfigError

    with pytest.raises(ConfigError, match=text) as err:
        parse_eval_args([str(tmp_path), *args])
    assert "\n" not in str(err.value)


def test_engine_defaults_to_jax(tmp_path):
    assert parse_eval_args([str(tmp_path)])[1].engine == "jax"

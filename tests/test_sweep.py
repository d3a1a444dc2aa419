"""Sweeps: one grid point equals the single run with its settings; bad grids are refused up front."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coherent_jax import sweep, train
from coherent_jax.config import SWEEPABLE, ConfigError, parse_overrides

TINY = [
    "env=pointmass",
    "num_envs=4",
    "unroll_length=8",
    "num_minibatches=2",
    "eval_episodes=2",
    "episode_length=50",
    "total_steps=96",
    "eval_every=2",
    "progress=false",
]


def read_rows(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def assert_rows_close(rows, expected):
    assert [r["iteration"] for r in rows] == [r["iteration"] for r in expected]
    for row, ref in zip(rows, expected, strict=True):
        assert row.keys() == ref.keys()
        for key in ref:
            if key == "time_s":
                continue
            if ref[key] is None:  # non-finite (e.g. no episode ended)
                assert row[key] is None, key
            else:
                assert row[key] == pytest.approx(ref[key], rel=1e-4, abs=1e-5), key


def test_sweep_point_equals_single_run(tmp_path):
    """Point (ent_coef=0.5, lr=1e-3, seed=1) of a vmapped 2x2x2 grid logs the metrics of that single run.

    Action noise keeps the compile short; that beta (coherent) reaches the program only
    through the same state hyperparameters is `test_sweepable_keys_enter_only_through_state_hparams`.
    """
    out = tmp_path / "sweep"
    argv = [*TINY, "seeds=2", "ent_coef=[0,0.5]", "lr=[3e-4,1e-3]", f"run_dir={out}"]
    assert sweep.main(argv) == 0
    names = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert len(names) == 8 and names[7] == "p007-ent_coef=0.5-lr=0.001-seed=1", names
    for name in names:
        assert sorted(p.name for p in (out / name).iterdir()) == [
            "config.yaml",
            "metrics.jsonl",
            "params.msgpack",
            "summary.json",
        ]
    single = tmp_path / "single"
    assert train.main([*TINY, "seed=1", "ent_coef=0.5", "lr=1e-3", f"run_dir={single}"]) == 0
    expected = read_rows(single / "metrics.jsonl")
    # Its config.yaml is the single run's (its own run directory, its seed and values).
    point_yaml = (out / names[7] / "config.yaml").read_text().replace(str(out / names[7]), "RUN")
    assert point_yaml == (single / "config.yaml").read_text().replace(str(single), "RUN")
    assert "eval/episode_return" in expected[1]
    assert_rows_close(read_rows(out / names[7] / "metrics.jsonl"), expected)
    # The other seed of that setting is a different run (the grid is not one point copied).
    other = read_rows(out / names[6] / "metrics.jsonl")
    assert other[-1]["train/value_loss"] != pytest.approx(expected[-1]["train/value_loss"], rel=1e-3)

    # Aggregate: mean and population std over the two seeds, recomputed from the point summaries.
    summaries = {n: json.loads((out / n / "summary.json").read_text()) for n in names}
    result = json.loads((out / "sweep.json").read_text())
    assert result["num_points"] == 8 and result["seeds"] == [0, 1]
    assert len(result["rows"]) == 4
    for i, (ent_coef, lr) in enumerate([(0.0, 3e-4), (0.0, 1e-3), (0.5, 3e-4), (0.5, 1e-3)]):
        returns = np.array([summaries[names[2 * i + s]]["final_eval_return"] for s in (0, 1)], np.float64)
        row = result["rows"][i]
        assert (row["ent_coef"], row["lr"]) == (ent_coef, pytest.approx(lr))
        assert row["seeds"] == 2
        assert row["final_eval_return_mean"] == pytest.approx(returns.mean(), rel=1e-9)
        assert row["final_eval_return_std"] == pytest.approx(returns.std(), rel=1e-9, abs=1e-12)
    csv_lines = (out / "sweep.csv").read_text().splitlines()
    assert csv_lines[0].startswith("ent_coef,lr,seeds,final_eval_return_mean") and len(csv_lines) == 5


BAD = [
    (["foo=[1,2]"], "'foo'"),
    (["num_envs=[4,8]"], "'num_envs'"),
    (["policy_hidden=[[8],[16]]"], "'policy_hidden'"),
    (["beta=[]"], "'beta'"),
    (["beta=[0.5,]"], "'beta'"),
    (["explore=coherent", "beta=[0.5,2]"], "'beta'"),
    (["seeds=0"], "'seeds'"),
    (["seeds=2", "seed=[1,2]"], "'seeds'"),
    # Action noise has no beta: that axis would run identical points.
    (["explore=action", "beta=[0.01,0.5]"], "'beta'"),
]


@pytest.mark.parametrize("args,named", BAD)
def test_bad_sweeps_exit_2_naming_the_key_and_write_nothing(tmp_path, capsys, args, named):
    out = tmp_path / "sweep"
    assert sweep.main([*TINY, *args, f"run_dir={out}"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("error:") and named in err[0], err
    assert "allowed" in err[0] or "valid" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_cli_exit_status(tmp_path):
    """The module entry point returns status 2 on a shape setting given as a list."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run(
        [sys.executable, "-m", "coherent_jax.sweep", "unroll_length=[8,16]", f"run_dir={tmp_path / 's'}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 2 and "'unroll_length'" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_grid_is_the_product_with_seeds_innermost():
    plan = sweep.parse_sweep([*TINY, "seed=5", "seeds=3", "ent_coef=[0,0.01]", "gamma=[0.9,0.99]"])
    assert plan.axes == {"ent_coef": [0.0, 0.01], "gamma": [0.9, 0.99]}
    assert plan.seeds == [5, 6, 7]
    got = [(p.values["ent_coef"], p.values["gamma"], p.seed) for p in plan.points]
    want = [(e, g, s) for e in (0.0, 0.01) for g in (0.9, 0.99) for s in (5, 6, 7)]
    assert got == want
    assert all(
        p.cfg == parse_overrides([*TINY, f"ent_coef={e}", f"gamma={g}", f"seed={s}"])
        for p, (e, g, s) in zip(plan.points, want, strict=True)
    )
    with pytest.raises(ConfigError):
        sweep.parse_sweep(["seed=[]"])


def test_sweepable_keys_enter_only_through_state_hparams():
    """Changing a sweepable key changes init_hparams() and nothing in the traced iteration.

    If a trainer read one of them as a Python constant, a sweep would silently run
    every point with the shared config's value; the jaxpr would then differ. Coherent
    PPO reads every one of them.
    """
    import jax

    from coherent_jax.agents import make_trainer
    from coherent_jax.envs.vec_env import VecEnv

    def trace(cfg, env, eval_env):
        trainer = make_trainer(cfg, env, eval_env)
        state = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
        return trainer.init_hparams(), str(jax.make_jaxpr(trainer.iteration)(state))

    on_policy = {
        "lr": 1e-3,
        "gamma": 0.9,
        "gae_lambda": 0.8,
        "clip_eps": 0.3,
        "target_kl": 0.02,
        "vf_coef": 0.7,
        "ent_coef": 0.01,
        "beta": 0.5,
    }
    # Coherent-SAC reads these (and lr, gamma, beta) from its state's hparams.
    sac = {"lr": 1e-3, "gamma": 0.9, "beta": 0.5, "tau": 0.01, "temperature": 0.1}
    sac.update({"sigma_init": 0.2, "sigma_delta": 0.2, "sigma_alpha": 1.05})
    assert set(on_policy) | set(sac) == set(SWEEPABLE)
    sac_base = ["algo=sac", "policy_hidden=[16]", "value_hidden=[16]", "batch_size=8", "utd_ratio=0.25"]
    for base_overrides, changed in (
        ([*TINY, "explore=coherent", "target_kl=0.01"], on_policy),
        ([*TINY, *sac_base, "explore=coherent"], sac),
    ):
        base = parse_overrides(base_overrides)
        env = VecEnv(base.env, base.num_envs, base.episode_length)
        eval_env = VecEnv(base.env, base.eval_episodes, base.episode_length)
        hp0, jaxpr0 = trace(base, env, eval_env)
        for key, value in changed.items():
            hp, jaxpr = trace(parse_overrides([*base_overrides, f"{key}={value}"]), env, eval_env)
            differs = any(
                not np.array_equal(a, b)
                for a, b in zip(jax.tree.leaves(hp), jax.tree.leaves(hp0), strict=True)
            )
            assert differs, (base.algo, key)
            assert jaxpr == jaxpr0, (base.algo, key)

"""Sweeps: a grid point matches the single run with its settings (to rounding); bad grids are refused."""

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import child_env

from coherent_jax import sweep, train
from coherent_jax.config import (
    ALGOS,
    EXPLORES,
    SUPPORTED_ALGOS,
    SWEEPABLE,
    ConfigError,
    parse_overrides,
    sweepable,
)
from coherent_jax.run import training
from coherent_jax.run.rundir import read_metrics
from coherent_jax.run.sweep import Point, parse_sweep

TINY = [
    "env=pointmass",
    "num_envs=4",
    "unroll_length=8",
    "ppo.num_minibatches=2",
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


@pytest.mark.slow
def test_sweep_point_equals_single_run(tmp_path):
    """Point (ent_coef=0.5, lr=1e-3, seed=1) of a vmapped 2x2x2 grid logs the metrics of that single run.

    Action noise keeps the compile short; that beta (coherent) reaches the program only
    through the same state hyperparameters is `test_sweepable_keys_enter_only_through_state_hparams`.
    """
    out = tmp_path / "sweep"
    argv = [*TINY, "seeds=2", "ppo.ent_coef=[0,0.5]", "lr=[3e-4,1e-3]", f"run_dir={out}"]
    assert sweep.main(argv) == 0
    names = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert len(names) == 8 and names[7] == "p007-ent_coef=0.5-lr=0.001-seed=1", names
    for name in names:
        assert sorted(p.name for p in (out / name).iterdir()) == [
            "config.yaml",
            "metrics.jsonl",
            "params.msgpack",
            "summary.json",
            "tb",
        ]
    single = tmp_path / "single"
    assert train.main([*TINY, "seed=1", "ppo.ent_coef=0.5", "lr=1e-3", f"run_dir={single}"]) == 0
    expected = read_rows(single / "metrics.jsonl")
    # Its config.yaml is the single run's (its own run directory, its seed and values).
    point_yaml = (out / names[7] / "config.yaml").read_text().replace(str(out / names[7]), "RUN")
    assert point_yaml == (single / "config.yaml").read_text().replace(str(single), "RUN")
    assert "eval/episode_return" in expected[1]
    assert_rows_close(read_rows(out / names[7] / "metrics.jsonl"), expected)
    # The other seed of that setting is a different run (the grid is not one point copied).
    other = read_rows(out / names[6] / "metrics.jsonl")
    assert other[-1]["train/value_loss"] != pytest.approx(expected[-1]["train/value_loss"], rel=1e-3)

    # Aggregate: mean and sample std (ddof 1) over the two seeds, recomputed from the point summaries.
    summaries = {n: json.loads((out / n / "summary.json").read_text()) for n in names}
    result = json.loads((out / "sweep.json").read_text())
    assert result["num_points"] == 8 and result["seeds"] == [0, 1]
    assert len(result["rows"]) == 4
    for i, (ent_coef, lr) in enumerate([(0.0, 3e-4), (0.0, 1e-3), (0.5, 3e-4), (0.5, 1e-3)]):
        returns = np.array([summaries[names[2 * i + s]]["final_eval_return"] for s in (0, 1)], np.float64)
        row = result["rows"][i]
        assert (row["ppo.ent_coef"], row["lr"]) == (ent_coef, pytest.approx(lr))
        assert row["seeds"] == 2
        assert row["final_eval_return_mean"] == pytest.approx(returns.mean(), rel=1e-9)
        assert row["final_eval_return_std"] == pytest.approx(returns.std(ddof=1), rel=1e-9, abs=1e-12)
    csv_lines = (out / "sweep.csv").read_text().splitlines()
    assert csv_lines[0].startswith("ppo.ent_coef,lr,seeds,final_eval_return_mean") and len(csv_lines) == 5


BAD = [
    (["foo=[1,2]"], "'foo'"),
    (["num_envs=[4,8]"], "'num_envs'"),
    (["policy_hidden=[[8],[16]]"], "'policy_hidden'"),
    (["coherent.beta=[]"], "'coherent.beta'"),
    (["coherent.beta=[0.5,]"], "'coherent.beta'"),
    (["explore=coherent", "coherent.beta=[0.5,2]"], "'coherent.beta'"),
    (["seeds=0"], "'seeds'"),
    (["seeds=2", "seed=[1,2]"], "'seeds'"),
    # Action noise has no beta: that axis would run identical points.
    (["explore=action", "coherent.beta=[0.01,0.5]"], "'coherent.beta'"),
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
    env = child_env()
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
    plan = parse_sweep([*TINY, "seed=5", "seeds=3", "ppo.ent_coef=[0,0.01]", "gamma=[0.9,0.99]"])
    assert plan.axes == {"ppo.ent_coef": [0.0, 0.01], "gamma": [0.9, 0.99]}
    assert plan.seeds == [5, 6, 7]
    got = [(p.values["ppo.ent_coef"], p.values["gamma"], p.seed) for p in plan.points]
    want = [(e, g, s) for e in (0.0, 0.01) for g in (0.9, 0.99) for s in (5, 6, 7)]
    assert got == want
    assert all(
        p.cfg == parse_overrides([*TINY, f"ppo.ent_coef={e}", f"gamma={g}", f"seed={s}"])
        for p, (e, g, s) in zip(plan.points, want, strict=True)
    )
    with pytest.raises(ConfigError):
        parse_sweep(["seed=[]"])


@pytest.mark.slow
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
        "ppo.gae_lambda": 0.8,
        "ppo.clip_eps": 0.3,
        "ppo.target_kl": 0.02,
        "ppo.vf_coef": 0.7,
        "ppo.ent_coef": 0.01,
        "coherent.beta": 0.5,
    }
    # Coherent-SAC reads these (and lr, gamma, beta) from its state's hparams.
    sac = {"lr": 1e-3, "gamma": 0.9, "coherent.beta": 0.5, "sac.tau": 0.01, "sac.temperature": 0.1}
    sac.update({"coherent_sac.sigma_init": 0.2, "coherent_sac.sigma_delta": 0.2})
    sac.update({"coherent_sac.sigma_alpha": 1.05})
    # With its own optimiser (vf_iters > 0) the value function also reads vf_lr.
    separate_value = {**on_policy, "ppo.vf_lr": 3e-4}
    # PSNE-SAC reads psne's sigma rule.
    sac_psne = {k: v for k, v in sac.items() if not k.startswith("coherent")}
    sac_psne.update({"psne.sigma_init": 0.2, "psne.sigma_delta": 0.2, "psne.sigma_alpha": 1.05})
    assert set(separate_value) | set(sac) | set(sac_psne) == set(SWEEPABLE)
    sac_base = [
        "algo=sac",
        "policy_hidden=[16]",
        "value_hidden=[16]",
        "sac.batch_size=8",
        "sac.utd_ratio=0.25",
    ]
    for base_overrides, changed in (
        ([*TINY, "explore=coherent", "ppo.target_kl=0.01"], on_policy),
        (
            [*TINY, "explore=coherent", "ppo.target_kl=0.01", "ppo.vf_lr=1e-3", "ppo.vf_iters=2"],
            separate_value,
        ),
        ([*TINY, *sac_base, "explore=coherent"], sac),
        ([*TINY, *sac_base, "explore=psne"], sac_psne),
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


def test_sweepable_declarations_match_every_trainer():
    """For every valid (algo, explore) pair, the fields' declarations name exactly the keys that reach the
    trainer's hyperparameters: a trainer built with every sweepable key changed holds the base trainer's
    hyperparameters with just the declared keys' leaves replaced (`training.point_hparams`), each of them
    changed. So a sweep needs no trainer per point, and refuses an axis a pair does not read."""
    import jax

    from coherent_jax.agents import make_trainer
    from coherent_jax.envs.vec_env import VecEnv

    changed = {"lr": 1e-3, "gamma": 0.9, "ppo.gae_lambda": 0.8, "ppo.clip_eps": 0.3, "ppo.target_kl": 0.02}
    changed.update({"ppo.vf_coef": 0.7, "ppo.ent_coef": 0.01, "coherent.beta": 0.5, "sac.tau": 0.01})
    changed.update({"sac.temperature": 0.1, "psne.sigma_init": 0.2, "psne.sigma_delta": 0.2})
    changed.update({"psne.sigma_alpha": 1.05, "ppo.vf_lr": 3e-4})
    changed.update({"coherent_sac.sigma_init": 0.2, "coherent_sac.sigma_delta": 0.2})
    changed.update({"coherent_sac.sigma_alpha": 1.05})
    assert set(changed) == set(SWEEPABLE)
    env = VecEnv("pointmass", 4, 50)
    eval_env = VecEnv("pointmass", 2, 50)
    small = ["policy_hidden=[4]", "value_hidden=[4]", "sac.batch_size=8", "sac.utd_ratio=0.25"]
    # vf_lr is in the state only with the value's own optimiser (vf_iters > 0); with the
    # joint loss a vf_lr > 0 is refused, so a sweep cannot vary it there.
    separate = ["ppo.vf_lr=1e-3", "ppo.vf_iters=2"]
    for explore in EXPLORES:
        for algo in SUPPORTED_ALGOS[explore]:
            assert algo in ALGOS
            for mode in ([], separate) if algo != "sac" else ([],):
                args = [*TINY, f"algo={algo}", f"explore={explore}", *small, *mode]
                base_hp = make_trainer(parse_overrides(args), env, eval_env).init_hparams()
                changes = {k: v for k, v in changed.items() if k != "ppo.vf_lr" or mode}
                if not mode:
                    with pytest.raises(ConfigError, match="'ppo.vf_iters'"):
                        parse_overrides([*args, "ppo.vf_lr=3e-4"])
                cfg = parse_overrides([*args, *(f"{k}={v}" for k, v in changes.items())])
                own = make_trainer(cfg, env, eval_env).init_hparams()
                declared = {k: v for k, v in changes.items() if sweepable(k).read_by(algo, explore)}
                derived = training.point_hparams(base_hp, Point(index=0, values=declared, seed=0, cfg=cfg))
                assert jax.tree.structure(derived) == jax.tree.structure(own)
                for a, b in zip(jax.tree.leaves(derived), jax.tree.leaves(own), strict=True):
                    assert a.dtype == b.dtype and np.array_equal(a, b), (algo, explore)
                for key in declared:  # each declared key's leaf really moved
                    one = training.point_hparams(base_hp, Point(0, {key: changed[key]}, 0, cfg))
                    moved = [
                        not np.array_equal(a, b)
                        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(base_hp), strict=True)
                    ]
                    assert sum(moved) == 1, (algo, explore, key)


# A2C with tiny networks: a few seconds to compile. 60 iterations per point.
SMALL = [
    "env=pointmass",
    "algo=a2c",
    "num_envs=2",
    "ppo.num_minibatches=1",
    "unroll_length=4",
    "eval_episodes=2",
    "episode_length=20",
    "policy_hidden=[8]",
    "value_hidden=[8]",
    "progress=false",
    "total_steps=480",
    "eval_every=7",
    "checkpoint_every=3",
]


def spawn_sweep(args, cwd):
    env = child_env()
    return subprocess.Popen(
        [sys.executable, "-m", "coherent_jax.sweep", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def point_rows(out):
    return {
        p.name: [{k: v for k, v in r.items() if k != "time_s"} for r in read_metrics(p / "metrics.jsonl")]
        for p in sorted(out.iterdir())
        if p.is_dir()
    }


@pytest.mark.slow
def test_sweep_killed_and_resumed_equals_an_uninterrupted_one(tmp_path):
    """SIGKILL a 2x2 sweep mid-run, resume=SWEEP_DIR: every point's metrics and parameters equal those
    of the same sweep run without interruption."""
    grid = [*SMALL, "lr=[3e-4,1e-3]", "seeds=2"]
    out = tmp_path / "sweep"
    proc = spawn_sweep([*grid, f"run_dir={out}"], tmp_path)
    first = out / "p000-lr=0.0003-seed=0" / "metrics.jsonl"
    t_end = time.monotonic() + 600
    while not (first.exists() and len(read_metrics(first)) >= 8):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < t_end, "no progress"
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = len(read_metrics(first))
    assert 8 <= killed_at < 60 and not (out / "sweep.json").exists()

    assert sweep.main([f"resume={out}"]) == 0
    ref = tmp_path / "ref"
    assert sweep.main([*grid, f"run_dir={ref}"]) == 0
    resumed, reference = point_rows(out), point_rows(ref)
    assert list(resumed) == list(reference) and len(reference) == 4
    for name, rows in reference.items():
        assert [r["iteration"] for r in rows] == list(range(1, 61)), name
        assert resumed[name] == rows, name
        assert (out / name / "params.msgpack").read_bytes() == (ref / name / "params.msgpack").read_bytes()
    result = json.loads((out / "sweep.json").read_text())
    assert result["resumed_from"] is not None and 0 < result["resumed_from"] <= killed_at
    assert result["rows"] == json.loads((ref / "sweep.json").read_text())["rows"]


@pytest.mark.slow
def test_diverged_point_is_named_and_the_others_continue(tmp_path, capsys):
    """lr=1e30 diverges at iteration 2; the sweep names that point, stops its rows, keeps the other
    point's metrics equal to its single run, and exits with status 3."""
    out = tmp_path / "sweep"
    # The command line refuses a key given twice: SMALL's budget and interval are replaced.
    args = [*(a for a in SMALL if a.split("=")[0] not in ("total_steps", "checkpoint_every"))]
    args += ["total_steps=80", "checkpoint_every=4"]
    assert sweep.main([*args, "lr=[3e-4,1e30]", f"run_dir={out}"]) == 3
    captured = capsys.readouterr()
    bad = "p001-lr=1e+30-seed=0"
    assert f"point {bad} diverged at iteration 2" in captured.err
    rows = point_rows(out)
    assert [r["iteration"] for r in rows[bad]] == [1]
    assert [r["iteration"] for r in rows["p000-lr=0.0003-seed=0"]] == list(range(1, 11))
    result = json.loads((out / "sweep.json").read_text())
    assert list(result["diverged"]) == [bad]
    summary = json.loads((out / bad / "summary.json").read_text())
    assert summary["final_eval_return"] is None and "iteration 2" in summary["diverged"]
    assert [r["non_finite"] for r in result["rows"]] == [0, 1]

    single = tmp_path / "single"
    assert train.main([*args, "lr=3e-4", f"run_dir={single}"]) == 0
    assert_rows_close(
        read_metrics(out / "p000-lr=0.0003-seed=0" / "metrics.jsonl"), read_metrics(single / "metrics.jsonl")
    )

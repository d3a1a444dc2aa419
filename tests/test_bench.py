"""The benchmark command: a tiny end-to-end run of the coherent suite, and its input errors."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import child_env

from benchmarks import coherent, throughput
from coherent_jax.exploration.coherent.reference import dense_log_marginals, sample_segments

TINY = [
    "env=pointmass",
    "num_envs=4",
    "unroll_length=8",
    "episode_length=20",
    "ppo.num_minibatches=2",
    "iterations=1",
    "filter_q=[8]",
    "filter_T=16",
    "filter_repeats=2",
    "seg_repeats=2",
    "chains=[episode]",
    "chain_iterations=1",
]


def _positive(value) -> bool:
    return isinstance(value, int | float) and math.isfinite(value) and value > 0


@pytest.mark.slow
def test_coherent_suite_writes_every_figure(tmp_path):
    """Every figure of the suite is a positive finite number, and block and dense filters agree."""
    out = tmp_path / "results" / "coherent.json"
    result = coherent.run([*TINY, f"out={out}"], log=lambda msg: None)
    assert json.loads(out.read_text()) == json.loads(json.dumps(result))
    assert sorted(p.name for p in out.parent.iterdir()) == ["coherent.json"]  # no temp file left
    data = json.loads(out.read_text())

    for key in ("suite", "timestamp", "jax_version", "device", "settings", "training", "filter"):
        assert data[key], key
    assert data["settings"]["config"]["env"] == "pointmass"
    assert data["settings"]["iterations"] == 1

    training = data["training"]
    for name in ("action", "coherent"):
        run = training[name]
        for key in ("compile_s", "iteration_s_median", "env_steps_per_s", "env_steps_per_s_total"):
            assert _positive(run[key]), (name, key)
        assert len(run["iteration_s"]) == 1
    for name in ("action", "coherent", "coherent_remat"):
        assert _positive(training[name]["compile_s"])
        assert _positive(training[name]["memory"]["peak_bytes"]), name
    assert _positive(training["ratio_coherent_over_action"])
    assert training["env_steps_per_iteration"] == 4 * 8

    segment = data["segment_log_prob"]
    for name in ("action", "coherent"):
        assert _positive(segment[name]["forward_ms"]) and _positive(segment[name]["grad_ms"])
    assert _positive(segment["ratio_grad_coherent_over_action"])

    (case,) = data["filter"]["cases"]
    assert case["q"] == 8 and data["filter"]["T"] == 16
    for method in ("block", "dense"):
        for key in ("forward_ms", "grad_ms", "compile_forward_s", "compile_grad_s"):
            assert _positive(case[method][key]), (method, key)
        assert _positive(case[method]["memory_grad"]["peak_bytes"])
    assert _positive(case["speedup_forward"]) and _positive(case["speedup_grad"])
    assert case["max_abs_logp_diff"] < 1e-3
    assert case["max_rel_grad_diff"] < 1e-3

    (chain,) = data["chains"].values()
    assert list(data["chains"]) == ["episode"] and chain["gradient"] == "episode"
    assert (chain["num_envs"], chain["unroll_length"]) == (4, 8)
    # One whole episode cycle (20 steps in segments of 8: 3 iterations), by its mean.
    assert chain["timed_iterations"] == 3 and chain["statistic"] == "mean"
    for name in ("action", "coherent"):
        for key in ("iteration_s", "iteration_s_median", "env_steps_per_s", "compile_s"):
            assert _positive(chain[name][key]), (name, key)
        cfg = data["settings"]["config"]
        assert 1 <= chain[name]["policy_steps"] <= cfg["ppo"]["num_epochs"] * cfg["ppo"]["num_minibatches"]
    assert _positive(chain["ratio_coherent_over_action"])

    table = coherent.format_table(data)
    assert "coherent/action" in table and "dense" in table and "4. long chains" in table


def test_long_chain_rows_are_the_preset_and_the_episode_gradient():
    """The ``thesis`` row is ``preset=thesis`` on the suite's task and seed (its buffer
    scored from its start, the chain through env resets), the ``episode`` row the suite's
    own settings with the episode gradient; an unknown row is refused."""
    from benchmarks.chains import chain_config, timed_iterations
    from coherent_jax.config import parse_overrides

    cfg = parse_overrides(["env=hopper", "seed=7", "num_envs=16"])
    thesis = chain_config(cfg, "thesis")
    assert (thesis.env, thesis.seed, thesis.num_envs, thesis.unroll_length) == ("hopper", 7, 4, 1000)
    assert thesis.preset == "thesis" and thesis.coherent.gradient == "exact"
    assert not thesis.coherent.episode_restart
    episode = chain_config(cfg, "episode")
    assert episode.coherent.gradient == "episode" and episode.num_envs == 16
    # The episode row's cost rises with the prefix: it is timed over whole episode cycles.
    assert timed_iterations(episode, "episode", 5) == 16  # 1,000 steps in segments of 64
    assert timed_iterations(episode, "episode", 17) == 32
    assert timed_iterations(thesis, "thesis", 5) == 5
    with pytest.raises(ValueError, match="'stored'"):
        chain_config(cfg, "stored")


@pytest.mark.slow
def test_dense_reference_checkpointed_equals_plain_and_block():
    """The chunk-checkpointed dense scan (used when its gradient would not fit) is the same function."""
    import jax
    import jax.numpy as jnp

    from coherent_jax.exploration.chain import ChainParams
    from coherent_jax.exploration.coherent.filter import log_marginals

    x, a, first, mu, w_std, action_std, beta = sample_segments(
        jax.random.PRNGKey(1), 1, 12, 5, 3, 0.3, 0.1, 0.2
    )
    x, a, first = x[0], a[0], first[0]

    def value_and_grad(fn, **kw):
        total = lambda m, s: jnp.sum(fn(x, a, first, ChainParams(m, s, action_std, beta), **kw))
        return jax.jit(jax.value_and_grad(total, argnums=(0, 1)))(mu, w_std)

    plain = value_and_grad(dense_log_marginals)
    for other in (value_and_grad(dense_log_marginals, checkpoint_chunk=4), value_and_grad(log_marginals)):
        for u, v in zip(jax.tree.leaves(plain), jax.tree.leaves(other), strict=True):
            assert jnp.allclose(u, v, rtol=1e-4, atol=1e-4)


def run_cli(args, cwd):
    env = child_env()
    return subprocess.run(
        [sys.executable, "-m", "benchmarks", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )


@pytest.mark.parametrize(
    "args,named",
    [
        (["speed"], "'speed'"),
        # No suite named runs the default (throughput) suite: its keys are checked.
        (["iterations=0"], "'iterations'"),
        (["coherent", "foo=1"], "'foo'"),
        (["coherent", "iterations=0"], "'iterations'"),
        (["coherent", "filter_q=[8,x]"], "'filter_q'"),
        (["coherent", "chains=[thesis,stored]"], "'chains'"),
        (["coherent", "env=cheetah"], "'env'"),
        (["coherent", "explore=action"], "'explore'"),
        (["coherent", "policy_hidden=[64,"], "'policy_hidden'"),
        (["sac", "sac.warmup_steps=5"], "'sac.warmup_steps'"),
        (["physics", "envs=[3]", "variants=[mjx_2dev]"], "'envs'"),
        (["strategies", "strategies=[action,action]"], "'strategies'"),
        (["strategies", "strategies=[action,bogus]"], "'strategies'"),
        (["strategies", "algo=sac", "strategies=[action,noisynet]"], "'strategies'"),
        (["strategies", "explore=gsde"], "'explore'"),
        (["strategies", "sac.warmup_steps=5"], "'sac.warmup_steps'"),
    ],
)
def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, named):
    from benchmarks.__main__ import main

    assert main([*args, f"out={tmp_path / 'r.json'}"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and named in lines[0], lines
    assert "allowed" in lines[0] or "valid" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_cli_entry_point_exits_2_and_writes_nothing(tmp_path):
    """``python -m benchmarks`` itself (the cases above run its `main` in-process)."""
    proc = run_cli(["coherent", "coherent.layers=every", f"out={tmp_path / 'r.json'}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "'coherent.layers'" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_throughput_suite_writes_every_row(tmp_path):
    """Raw env, PPO and Coherent-PPO rows with positive rates, compile times, memory and ratios.

    Brax's PPO (about a minute of compiling even here) and the SAC rows are left to
    the full bench; their skip reasons are recorded.
    """
    out = tmp_path / "results" / "throughput.json"
    args = ["env=pointmass", "num_envs=4", "unroll_length=8", "ppo.num_minibatches=2", "iterations=2"]
    only_ppo = "rows=[ppo,coherent_ppo]"
    result = throughput.run([*args, only_ppo, f"out={out}"], log=lambda msg: None)
    assert json.loads(out.read_text()) == json.loads(json.dumps(result))
    assert sorted(p.name for p in out.parent.iterdir()) == ["throughput.json"]
    data = json.loads(out.read_text())
    assert data["suite"] == "throughput" and data["env_steps_per_iteration"] == 32
    rows = data["rows"]
    assert sorted(rows) == ["coherent_ppo", "ppo", "raw_env"]
    for name, row in rows.items():
        for key in ("compile_s", "iteration_s_median", "env_steps_per_s", "env_steps_per_s_best"):
            assert _positive(row[key]), (name, key)
        assert len(row["iteration_s"]) == 2
        assert row["env_steps_per_s"] == pytest.approx(32 / row["iteration_s_median"])
        assert row["env_steps_per_s_best"] == pytest.approx(32 / min(row["iteration_s"]))
    for name in ("ppo", "coherent_ppo"):
        assert _positive(rows[name]["memory"]["peak_bytes"]), name
        assert rows[name]["config"]["num_envs"] == 4
    assert (
        rows["ppo"]["config"]["explore"] == "action"
        and rows["coherent_ppo"]["config"]["explore"] == "coherent"
    )
    ratios = data["ratios"]
    assert ratios["ppo_over_raw_env"] == pytest.approx(
        rows["ppo"]["env_steps_per_s"] / rows["raw_env"]["env_steps_per_s"]
    )
    assert "ppo_over_brax_ppo" not in ratios
    assert data["skipped"] == {n: "not in rows=" for n in ("sac", "coherent_sac", "brax_ppo")}
    assert ratios["coherent_ppo_over_ppo"] == pytest.approx(
        rows["coherent_ppo"]["env_steps_per_s"] / rows["ppo"]["env_steps_per_s"]
    )
    table = throughput.format_table(data)
    assert "Brax PPO" in table and "skipped: not in rows=" in table and "PPO (ours) / raw env" in table


@pytest.mark.parametrize(
    "args,named",
    [
        (["algo=sac"], "'algo'"),
        (["explore=coherent"], "'explore'"),
        (["rows=[ppo,trpo]"], "'rows'"),
        (["rows=[]"], "'rows'"),
        (["filter_q=[8]"], "'filter_q'"),
        (["num_envs=0"], "'num_envs'"),
    ],
)
def test_throughput_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, named):
    """The same checks in-process (the subprocess test above covers the entry point)."""
    from benchmarks.__main__ import main

    for argv in (["throughput", *args], args):  # the suite named, and the default
        assert main([*argv, f"out={tmp_path / 'r.json'}"]) == 2
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error:") and named in lines[0], lines
        assert "allowed" in lines[0] or "valid" in lines[0]
        assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suite", ["throughput", "coherent", "sac", "strategies", "physics"])
def test_every_suite_checks_its_output_path_first(tmp_path, capsys, suite):
    """A location that cannot be written is refused in one line before any work, not at the end."""
    from benchmarks.__main__ import main

    (tmp_path / "a_file").write_text("keep")
    for bad in (tmp_path / "a_file" / "r.json", tmp_path, Path("/proc/r.json")):
        assert main([suite, f"out={bad}"]) == 2
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(lines) == 1 and "'out'" in lines[0] and "allowed" in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_training_keys_pass_through_including_dotted_ones():
    """Every training key reaches the config, the ``coherent.*`` group too; a bad one is refused."""
    from coherent_jax.config import ConfigError

    items = ["coherent.beta=0.1", "coherent.integration=mc", "coherent.layers=all"]
    # The episode row is the analytic chain's: with mc integration it is refused before anything runs.
    with pytest.raises(ConfigError, match="'chains': 'episode'.*'coherent.gradient'"):
        coherent.parse(items)
    cfg = coherent.parse([*items, "chains=[thesis]"]).config
    assert (cfg.coherent.beta, cfg.coherent.integration, cfg.coherent.layers) == (0.1, "mc", "all")
    assert throughput.parse(["coherent.integration=mc"]).config.coherent.integration == "mc"
    with pytest.raises(ConfigError, match="'coherent.integration'"):
        coherent.parse(["coherent.integration=exact"])
    # The sac suite checks the config with Coherent-SAC too, before anything runs.
    from benchmarks import sac

    with pytest.raises(ConfigError, match="'coherent.integration'"):
        sac.parse(["coherent.integration=analytic"])


@pytest.mark.parametrize("task", ["hopper", "brax-hopper"])
def test_physics_mjx_ls50_sets_the_line_search_of_either_kind_of_mjx_task(task):
    """``bench physics``'s ``mjx_ls50`` rows: Gymnasium's tasks on MJX keep their model as
    ``model``, Brax's as ``sys``; both get the line-search iterations the row names."""
    from benchmarks.physics import set_ls_iterations
    from coherent_jax.envs.vec_env import VecEnv

    env = VecEnv(task, 2, physics="mjx")
    set_ls_iterations(env, 7)
    model = env.env.sys if hasattr(env.env, "sys") else env.env.model
    assert int(model.opt.ls_iterations) == 7

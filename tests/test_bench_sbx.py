"""The sbx benchmark: our settings under SBX's names, the figures and ratios from given times,
refusals before anything runs (a venv that is missing among them), and, where SBX's venv
exists, a tiny real run of both sides."""

import io
import json

import pytest
from helpers import TINY_BENCH_SAC

from benchmarks import sbx, sbx_process
from coherent_jax.config import to_dict


def settings(*items):
    bench, cfg, _ = sbx.parse([*items, "install=true"])
    return cfg, sbx.sbx_settings(cfg)


def test_settings_map_to_sbx_names():
    cfg, s = settings(
        "num_envs=4",
        "unroll_length=8",
        "sac.utd_ratio=0.5",
        "sac.batch_size=64",
        "sac.warmup_steps=64",
        "sac.buffer_size=5000",
        "policy_hidden=[64,32]",
        "value_hidden=[128]",
        "activation=tanh",
        "lr=0.001",
        "gamma=0.98",
        "sac.tau=0.01",
        "seed=3",
    )
    assert s["env_id"] == "HalfCheetah-v5" and s["num_envs"] == 4 and s["seed"] == 3
    assert s["episode_length"] == 1000
    assert s["sac"] == {
        "learning_rate": 0.001,
        "buffer_size": 5000,
        "learning_starts": 63,  # SB3 trains once num_timesteps > learning_starts
        "batch_size": 64,
        "tau": 0.01,
        "gamma": 0.98,
        "train_freq": [8, "step"],
        "gradient_steps": 16,  # 0.5 x 4 envs x 8 steps
        "policy_delay": 1,
        "ent_coef": 0.2,
        "target_entropy": "auto",
        "policy_kwargs": {"net_arch": {"pi": [64, 32], "qf": [128]}, "activation_fn": "tanh"},
    }
    # 64 warm-up steps are 2 iterations of 32, the second updates; two more after it.
    assert s["warmup_iterations"] == sbx.warmup_iterations(cfg) == 4


def test_temperature_episode_length_and_task_names_map():
    _, s = settings("sac.auto_temperature=true", "sac.temperature=0.5", "sac.target_entropy=-3")
    assert s["sac"]["ent_coef"] == "auto_0.5" and s["sac"]["target_entropy"] == -3.0
    _, s = settings("env=Reacher-v5", "episode_length=0")
    assert s["env_id"] == "Reacher-v5" and s["episode_length"] == 50  # the task's own
    cfg, s = settings()  # the suite's defaults: no random-action warm-up
    assert s["sac"]["learning_starts"] == 0 and s["warmup_iterations"] == 3
    assert s["sac"]["gradient_steps"] == s["num_envs"] * s["sac"]["train_freq"][0] == 128
    assert sbx.gym_id("hopper") == "Hopper-v5" and sbx.gym_id("brax-hopper") is None


def test_held_mismatches_name_what_sbx_built_differently():
    _, s = settings()
    held = {
        "n_envs": 8,
        "env_steps_per_iteration": 128,
        "gradient_steps": 128,
        "batch_size": 256,
        "buffer_size": 100000,
        "learning_starts": 0,
        "learning_rate": 0.0003,
        "qf_learning_rate": 0.0003,
        "gamma": 0.99,
        "tau": 0.005,
        "policy_delay": 1,
        "ent_coef": 0.2,
        "target_entropy": -6.0,
        "net_arch_pi": [256, 256],
        "net_arch_qf": [256, 256],
        "n_critics": 2,
        "activation_fn": "relu",
        "max_episode_steps": 1000,
    }
    assert sbx.held_mismatches(s, held, action_size=6) == []
    wrong = sbx.held_mismatches(s, {**held, "gradient_steps": 1, "n_critics": 3}, action_size=6)
    assert [w.split(":")[0] for w in wrong] == ["gradient_steps", "n_critics"]


def timed(iteration_s, collect=0.1, train=True):
    record = {"iteration_s": iteration_s, "collect_s": [collect] * len(iteration_s)}
    if train:  # SBX times its training within the iteration
        record["train_s"] = [t - collect for t in iteration_s]
    return record


def test_summary_ratios_are_ours_over_sbx():
    ours = {
        "iteration": {"compile_s": 40.0, "warmup_call_s": 9.0, "memory": None},
        "collect_only": {"compile_s": 10.0, "warmup_call_s": 1.0, "memory": None},
    }
    ours_rounds = [
        timed([1.0, 1.0], 0.05, False),
        timed([2.0, 2.0], 0.05, False),
        timed([1.0, 3.0], 0.05, False),
    ]
    sbx_rounds = [timed([2.0, 2.0]), timed([3.0, 3.0]), timed([4.0, 4.0])]
    ready = {"setup_s": 5.0, "warmup": {"iteration_s": [30.0, 9.0, 3.5]}, "versions": {}, "held": {}}
    tr = sbx.summarize(128, 64, ours, ours_rounds, ready, sbx_rounds)
    o, x = tr["ours"], tr["sbx"]
    assert o["iteration_s_median"] == 1.5 and x["iteration_s_median"] == 3.0
    assert o["env_steps_per_s"] == pytest.approx(128 / 1.5)
    assert o["gradient_updates_per_s"] == pytest.approx(64 / 1.5)
    assert x["env_steps_per_s"] == pytest.approx(128 / 3.0)
    assert tr["ratio_env_steps_per_s"] == tr["ratio_gradient_updates_per_s"] == pytest.approx(2.0)
    assert tr["round_ratios"] == pytest.approx([2.0, 1.5, 2.0]) and tr["round_ratio_median"] == 2.0
    assert o["compile_s"] == 40.0 and o["compile_collect_only_s"] == 10.0
    assert x["compile_s"] == pytest.approx(27.0 + 6.0 + 0.5)  # warm-up above the median
    # Where the time goes: SBX's training as timed, ours' updates as iteration less collection.
    assert x["update_s_median"] == pytest.approx(2.9) and o["update_s_median"] == pytest.approx(1.45)
    assert tr["ratio_collect"] == pytest.approx(2.0) and tr["ratio_updates_alone"] == pytest.approx(2.0)
    assert x["update_only_updates_per_s"] == pytest.approx(64 / 2.9)
    assert o["collect_env_steps_per_s"] == pytest.approx(128 / 0.05)
    assert o["round_env_steps_per_s"] == pytest.approx([128.0, 64.0, 64.0])
    json.dumps(tr)  # what the suite writes
    cfg, s = settings()
    tr["sbx"].update(versions={"sbx-rl": "0.28.0"}, held={"vec_env": "DummyVecEnv"})
    machine = {"jax_version": "0.9.2", "device": "cpu", "cpu": "x", "cpu_count": 2}
    result = {
        **machine,
        "load_average_start": [1.0],
        "load_average_end": [2.0],
        "settings": {"config": to_dict(cfg)},
        "training": tr,
        "sbx_settings": s,
        "physics": "native",
    }
    table = sbx.format_table(result)
    assert "ours / SBX: 2.00x env steps/s and 2.00x updates/s" in table
    assert "per round 2.00, 1.50, 2.00 (median 2.00x)" in table and "collection alone 2.00x" in table


def test_driver_records_are_read_past_other_output():
    stream = io.StringIO('a library says hello\n@sbx {"ready": true, "x": [1, 2]}\n@sbx {"x": 3}\n')
    assert sbx_process.read_record(stream) == {"ready": True, "x": [1, 2]}
    assert sbx_process.read_record(stream) == {"x": 3}
    assert sbx_process.read_record(stream) is None


def test_venv_is_ready_only_with_the_current_requirements(tmp_path):
    venv = tmp_path / "v"
    assert not sbx_process.venv_ready(venv)
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").write_text("")
    assert not sbx_process.venv_ready(venv)  # no stamp: pip has not finished there
    (venv / sbx_process.STAMP).write_text("0" * 64 + "\n")
    assert not sbx_process.venv_ready(venv)  # made from other requirements
    (venv / sbx_process.STAMP).write_text(sbx_process.requirements_hash() + "\n")
    assert sbx_process.venv_ready(venv)
    assert sbx_process.venv_path("rel") == sbx_process.ROOT / "rel"
    assert sbx_process.venv_path(str(venv)) == venv


@pytest.mark.parametrize(
    "args,key",
    [
        (["explore=coherent"], "'explore'"),
        (["algo=ppo"], "'algo'"),
        (["env=brax-halfcheetah"], "invalid env"),
        (["env=pointmass"], "invalid env"),
        (["normalize_obs=true"], "'normalize_obs'"),
        (["sac.update_after=1000"], "'sac.update_after'"),
        (["rounds=0"], "'rounds'"),
        (["total_steps=1000"], "'total_steps'"),
        (["install=false", "venv=no-such-venv"], "'venv'"),
    ],
)
def test_bad_settings_exit_2_and_write_nothing(tmp_path, capsys, args, key):
    from benchmarks.__main__ import main

    assert main(["sbx", *args, f"out={tmp_path / 'r.json'}"]) == 2
    err = capsys.readouterr().err
    assert key in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_the_suite_is_listed_with_its_cost():
    from benchmarks.__main__ import help_text

    text = help_text()
    assert "sbx suite COST" in text and "install=true" in text


VENV = sbx_process.venv_path(sbx_process.DEFAULT_VENV)


@pytest.mark.slow
@pytest.mark.skipif(
    not sbx_process.venv_ready(VENV),
    reason="needs SBX's venv (.venv-sbx in the repository's root, which `python -m benchmarks sbx` "
    "makes from benchmarks/sbx-requirements.txt: about 2 GB with PyTorch); absent here",
)
def test_tiny_run_times_both_sides(tmp_path):
    out = tmp_path / "sbx.json"
    items = [
        "env=inverted_pendulum",
        "num_envs=2",
        "unroll_length=8",
        "policy_hidden=[16]",
        "value_hidden=[16]",
        *TINY_BENCH_SAC,
        "rounds=2",
        "iterations=2",
        "install=false",
        f"out={out}",
    ]
    result = sbx.run(items, log=lambda msg: None)
    tr = json.loads(out.read_text())["training"]
    assert tr["env_steps_per_iteration"] == 16 and tr["updates_per_iteration"] == 4
    assert [len(r) for r in tr["ours"]["iteration_s"]] == [2, 2]
    assert [len(r) for r in tr["sbx"]["iteration_s"]] == [2, 2]
    assert tr["sbx"]["held"]["vec_env"] == "DummyVecEnv" and tr["sbx"]["held"]["n_envs"] == 2
    assert tr["ratio_env_steps_per_s"] == pytest.approx(
        tr["sbx"]["iteration_s_median"] / tr["ours"]["iteration_s_median"]
    )
    assert "ours / SBX" in sbx.format_table(result)

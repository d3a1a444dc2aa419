"""What a new user meets in the first hour of configuring runs: ``--help`` and dry runs that
show the values presets resolve to, short refusals of typos and of a sweep's items given to
``train``, tasks of one's own checked before anything of theirs is called, and a SAC run
too short to leave its warm-up. Every refusal: one line, exit status 2, nothing written."""

import os
import textwrap

import pytest
import yaml
from helpers import ROOT

from coherent_jax import sweep, train
from coherent_jax.config import ConfigError, parse_overrides
from coherent_jax.config.checks import warmup_warning
from coherent_jax.run import launch, training
from coherent_jax.run.checkpoint import stored_config
from coherent_jax.run.loop_state import StopRequest
from coherent_jax.run.sweep import parse_sweep

EXAMPLE_FILE = ROOT / "examples" / "reacher_task.py"


def _help_value(text: str, key: str) -> str:
    """The value ``--help`` shows for `key` (its ``  key=value  help`` line)."""
    lines = [line.split()[0] for line in text.splitlines() if line.startswith(f"  {key}=")]
    assert len(lines) == 1, lines
    return lines[0].split("=", 1)[1]


def _refused(main, argv, capsys) -> str:
    """Runs `main(argv)` in the current directory, which must stay empty; the one error line."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert os.listdir(".") == []  # no run directory, no runs/
    return err[0]


# ------------------------------------------------------------------ row 5
def test_row5_help_shows_the_values_algo_and_preset_resolve_to(capsys):
    assert _help_value(train.train_help(), "num_envs") == "64"
    thesis = train.train_help(["preset=thesis"])
    assert _help_value(thesis, "num_envs") == "4" and _help_value(thesis, "unroll_length") == "1000"
    assert "values below: those of preset=thesis" in thesis
    sac = train.train_help(["preset=thesis", "algo=sac", "lr=0.002"])
    assert (_help_value(sac, "num_envs"), _help_value(sac, "sac.warmup_steps")) == ("1", "10000")
    assert _help_value(sac, "lr") == "0.002"  # any other item given before --help too
    assert _help_value(sweep.sweep_help(["algo=sac", "seeds=2"]), "num_envs") == "8"
    # Through the entry point, and a bad item before --help is refused like any other.
    assert train.main(["preset=thesis", "--help"]) == 0
    assert _help_value(capsys.readouterr().out, "num_envs") == "4"
    assert train.main(["preset=thesis", "num_env=3", "--help"]) == 2
    assert "unknown key 'num_env'" in capsys.readouterr().err


def test_row5_dry_run_prints_the_resolved_config_and_writes_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    items = ["env=pointmass", "preset=thesis", "algo=sac", f"run_dir={tmp_path / 'run'}"]
    for flag in ("dry_run=true", "--print-config"):
        assert train.main([*items, flag]) == 0
        out = capsys.readouterr().out
        assert yaml.safe_load(out) == stored_config(parse_overrides(items))  # what config.yaml would hold
        assert out.rstrip().endswith(f"nothing written; the run would write to {tmp_path / 'run'}")
        assert os.listdir(tmp_path) == []
    assert sweep.main(["env=pointmass", "seeds=2", "lr=[0.001,0.002]", "dry_run=true"]) == 0
    out = capsys.readouterr().out
    assert yaml.safe_load(out)["grid"] == {"axes": {"lr": [0.001, 0.002]}, "seeds": [0, 1], "points": 4}
    assert "the run would write to runs/sweep-pointmass-ppo-action-" in out
    assert os.listdir(tmp_path) == []
    assert "'dry_run': 'maybe' (allowed: true or false)" in _refused(train.main, ["dry_run=maybe"], capsys)


# ------------------------------------------------------------------ row 6
@pytest.mark.parametrize(
    "item, close",
    [
        ("total_step=1000", "total_steps"),
        ("temperatur=0.1", "sac.temperature"),
        ("ppo.clip=0.1", "ppo.clip_eps"),
    ],
)
def test_row6_a_typo_gets_one_short_line_with_close_keys(item, close, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    key = item.split("=")[0]
    for main in (train.main, sweep.main):  # every entry point, through one helper
        line = _refused(main, [item], capsys)
        assert line.startswith(f"error: unknown key {key!r} (did you mean {close}")
        assert line.endswith("; valid keys: --help lists them all") and len(line) < 150
        assert line.count(",") <= 2  # at most three candidates, never the list of keys


def test_row6_a_sweeps_items_given_to_train_point_to_the_sweep(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    seeds = _refused(train.main, ["env=pointmass", "seeds=2"], capsys)
    assert "invalid key 'seeds'" in seeds and "python -m coherent_jax.sweep seeds=2" in seeds
    lrs = _refused(train.main, ["env=pointmass", "lr=[1e-3,3e-4]"], capsys)
    assert "invalid value for 'lr'" in lrs and "python -m coherent_jax.sweep lr=[1e-3,3e-4]" in lrs
    shape = _refused(train.main, ["num_envs=[4,8]"], capsys)
    assert "'num_envs'" in shape and "cannot vary it" in shape
    # What the pointer says works, and a list setting still takes its one list.
    assert len(parse_sweep(["env=pointmass", "seeds=2", "lr=[1e-3,3e-4]"]).points) == 4
    assert parse_overrides(["policy_hidden=[32,32]"]).policy_hidden == [32, 32]


# ------------------------------------------------------------------ row 12
def test_row12_a_callable_not_declared_to_make_a_task_is_never_called(monkeypatch, tmp_path, capsys):
    calls = []
    monkeypatch.setattr(os, "system", lambda *args: calls.append(args))
    for name in ("os:system", "bad_user_tasks:unannotated", "os:getcwd", "bad_user_tasks:not_a_task"):
        with pytest.raises(ConfigError) as err:
            parse_overrides([f"env={name}"])
        msg = str(err.value)
        assert msg.startswith(f"invalid value for 'env': task {name!r}: ") and "\n" not in msg
        assert "not an MjcfTask, a subclass of it, or a function of no arguments annotated" in msg
        assert "called although" not in msg  # bad_user_tasks:unannotated raises if called
    assert calls == []
    monkeypatch.chdir(tmp_path)
    line = _refused(train.main, ["env=os:"], capsys)
    assert line.startswith("error: invalid value for 'env': 'os:' (allowed: MODULE:NAME or")
    assert "DictConfig" not in line


def test_row12_a_task_by_file_path_and_the_declared_forms(tmp_path, monkeypatch):
    (tmp_path / "arm.py").write_text(
        textwrap.dedent(
            """
            from __future__ import annotations

            import dataclasses

            from coherent_jax.envs import MjcfTask
            from examples.reacher_task import reacher


            def arm() -> MjcfTask:
                return dataclasses.replace(reacher, episode_length=30)


            @dataclasses.dataclass(frozen=True)
            class Arm(MjcfTask):
                mjcf: object = reacher.mjcf
                fields: tuple = reacher.fields
                observe: object = reacher.observe
                reward: object = reacher.reward
                episode_length: int = 40
            """
        )
    )
    monkeypatch.chdir(tmp_path)  # not the repository's root
    assert parse_overrides([f"env={EXAMPLE_FILE}:reacher"]).episode_length == 50
    assert parse_overrides(["env=arm.py:arm"]).episode_length == 30  # annotated (as a string) factory
    assert parse_overrides(["env=arm.py:Arm"]).episode_length == 40  # a subclass
    cfg = parse_overrides(["env=arm.py:arm"])
    assert str(launch.default_run_dir(cfg)).startswith(os.path.join("runs", "arm:arm-ppo-"))
    with pytest.raises(ConfigError, match=r"file 'nowhere\.py' not found"):
        parse_overrides(["env=nowhere.py:arm"])
    readme = (ROOT / "README.md").read_text()
    assert "env=examples/reacher_task.py:reacher" in readme


# ------------------------------------------------------------------ row 13
def test_row13_sac_within_its_warmup_is_warned_of_naming_both_numbers(tmp_path, monkeypatch, capsys):
    short = parse_overrides(["preset=thesis", "algo=sac", "total_steps=5000"])
    warning = warmup_warning(short)
    assert warning is not None and "total_steps=5000" in warning and "sac.warmup_steps=10000" in warning
    assert warmup_warning(parse_overrides(["preset=thesis", "algo=sac", "total_steps=20000"])) is None
    assert warmup_warning(parse_overrides(["algo=ppo", "total_steps=1000"])) is None
    # Rounded up to whole iterations: 10,001 steps of 50 per iteration leave the warm-up.
    assert warmup_warning(parse_overrides(["preset=thesis", "algo=sac", "total_steps=10001"])) is None
    monkeypatch.chdir(tmp_path)
    assert (
        train.main(["preset=thesis", "algo=sac", "total_steps=5000", "env=pointmass", "--print-config"]) == 0
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [warning]
    assert os.listdir(tmp_path) == []
    # A run warns too, once every input is accepted (training itself is left out here).
    monkeypatch.setattr(training, "train", lambda *args, **kwargs: {"stopped_by": None})
    with StopRequest() as stop:
        done = launch.launch_train(["preset=thesis", "algo=sac", "total_steps=5000", "env=pointmass"], stop)
    assert done.status == 0 and capsys.readouterr().err.strip().splitlines() == [warning]

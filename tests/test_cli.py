"""Command-line errors: one line naming the key and what is allowed, exit 2, nothing written."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import child_env

from coherent_jax.config import Config, ConfigError, parse_overrides

BAD = [
    (["foo=1"], "'foo'"),
    (["lr=abc"], "'lr'"),
    (["lr=-1"], "'lr'"),
    (["lr=nan"], "'lr'"),
    (["num_envs=0"], "'num_envs'"),
    (["num_envs=2.5"], "'num_envs'"),
    (["env=cheetah"], "'env'"),
    (["algo=trpo"], "'algo'"),
    (["explore=boltzmann"], "'explore'"),
    (["coherent.beta=1.5"], "'coherent.beta'"),
    (["gamma=-0.1"], "'gamma'"),
    (["normalize_obs=maybe"], "'normalize_obs'"),
    (["ppo.num_minibatches=3"], "'ppo.num_minibatches'"),
    (["policy_hidden=[0,64]"], "'policy_hidden'"),
    # strategies, the coherent.* group and refused pairs
    (["explore=coherent", "coherent.integration=exact"], "'coherent.integration'"),
    (["explore=coherent", "coherent.layers=first"], "'coherent.layers'"),
    (["explore=coherent", "coherent.layers=all"], "'coherent.integration'"),
    (["coherent.depth=2"], "'coherent.depth'"),
    (["algo=sac", "explore=noisynet"], "'algo'"),
    (["algo=sac", "explore=coherent", "coherent.integration=analytic"], "'coherent.integration'"),
    (["algo=sac", "explore=coherent", "coherent.integration=mc", "coherent.layers=all"], "'coherent.layers'"),
    (["explore=coherent", "coherent.integration=mc", "coherent.gradient=episode"], "'coherent.gradient'"),
    (["algo=sac", "explore=coherent", "coherent.gradient=stored"], "'coherent.gradient'"),
    (["gsde.resample_every=0"], "'gsde.resample_every'"),
    (["pink.exponent=-1"], "'pink.exponent'"),
    (["lattice.resample_every=0"], "'lattice.resample_every'"),
    (["lattice.init_std=20"], "'lattice.init_std'"),
    (["lattice.alpha=-1"], "'lattice.alpha'"),
    (["lattice.std_reg=-0.1"], "'lattice.std_reg'"),
    (["lattice.action_noise=maybe"], "'lattice.action_noise'"),
    (["explore=lattice", "lattice.action_noise=false", "lattice.alpha=0"], "'lattice.alpha'"),
    (["noisynet.sigma0=0"], "'noisynet.sigma0'"),
    (["lr"], "'lr'"),
    # YAML syntax errors in a value
    (["policy_hidden=[64,64"], "'policy_hidden'"),
    (["seed={"], "'seed'"),
    (["env="], "'env'"),
]


@pytest.mark.parametrize("overrides,key", BAD)
def test_bad_overrides_raise_naming_the_key(overrides, key):
    with pytest.raises(ConfigError) as err:
        parse_overrides(overrides)
    msg = str(err.value)
    assert key in msg
    assert "\n" not in msg


def test_error_names_allowed_values():
    with pytest.raises(ConfigError, match="halfcheetah"):
        parse_overrides(["env=cheetah"])
    with pytest.raises(ConfigError, match="halfcheetah, hopper"):
        parse_overrides(["env="])
    with pytest.raises(ConfigError, match="not valid YAML"):
        parse_overrides(["policy_hidden=[64,64"])
    with pytest.raises(ConfigError, match=r"\[0, 1\]"):
        parse_overrides(["coherent.beta=1.5"])


def test_good_overrides_are_typed():
    cfg = parse_overrides(["lr=1e-3", "num_envs=16", "policy_hidden=[32,32]", "normalize_obs=false"])
    assert cfg.lr == pytest.approx(1e-3) and isinstance(cfg.lr, float)
    assert cfg.num_envs == 16
    assert cfg.policy_hidden == [32, 32]
    assert cfg.normalize_obs is False
    # The defaults, with episode_length=0 resolved to the task's own time limit.
    assert parse_overrides([]) == dataclasses.replace(Config(), episode_length=1000)


def run_cli(args, cwd):
    env = child_env()
    return subprocess.run(
        [sys.executable, "-m", "coherent_jax.train", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )


@pytest.mark.parametrize("overrides,key", BAD[:8] + BAD[-4:])
def test_cli_bad_input_exits_2_and_writes_nothing(tmp_path, overrides, key):
    proc = run_cli([*overrides, f"run_dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and key in lines[0], proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_refuses_non_empty_run_dir(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "keep.txt").write_text("precious")
    proc = run_cli(["env=inverted_pendulum", f"run_dir={run}"], cwd=tmp_path)
    assert proc.returncode == 2
    assert "'run_dir'" in proc.stderr
    assert sorted(p.name for p in run.iterdir()) == ["keep.txt"]


def test_cli_help_lists_every_option_with_default(tmp_path):
    proc = run_cli(["--help"], cwd=tmp_path)
    assert proc.returncode == 0
    from coherent_jax.config import FIELDS, get_value

    for name in FIELDS:
        value = get_value(Config(), name)
        shown = "[" + ",".join(map(str, value)) + "]" if isinstance(value, list) else str(value)
        shown = str(value).lower() if isinstance(value, bool) else "null" if value is None else shown
        assert f"  {name}={shown} " in proc.stdout, name
    # What algo=sac changes is said beside each value it changes.
    assert "num_envs=64" in proc.stdout and "[algo=sac: 8]" in proc.stdout
    assert "coherent.integration=analytic" in proc.stdout and "[algo=sac: mc]" in proc.stdout


def test_cli_refused_pair_names_the_reason(tmp_path):
    proc = run_cli(["algo=sac", "explore=noisynet", f"run_dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "on-policy" in lines[0] and "explore=noisynet" in lines[0], proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_dotted_group_keys_and_sac_default():
    cfg = parse_overrides(["explore=coherent", "coherent.integration=mc", "coherent.layers=all"])
    assert (cfg.coherent.integration, cfg.coherent.layers) == ("mc", "all")
    assert parse_overrides(["algo=sac", "explore=coherent"]).coherent.integration == "mc"
    assert parse_overrides([]).coherent.integration == "analytic"


@pytest.mark.parametrize("where", ["under_a_file", "read_only"])
def test_cli_refuses_an_unwritable_run_dir_before_any_work(tmp_path, where):
    """A run directory that cannot be created or written: one line, exit 2, nothing left behind."""
    if where == "under_a_file":
        (tmp_path / "file.txt").write_text("x")
        run = tmp_path / "file.txt" / "run"
    else:
        run = Path("/sys/coherent_jax_run_dir_check/run")  # sysfs refuses new directories
    proc = run_cli(["env=pointmass", f"run_dir={run}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "'run_dir'" in lines[0] and "cannot be written" in lines[0], proc.stderr
    assert "compiling" not in proc.stdout
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == (["file.txt"] if where == "under_a_file" else []), left
    assert not run.exists()


def test_help_prints_options_grouped_and_every_field_declares_its_group():
    from coherent_jax.config import FIELDS, GROUPS, SECTIONS, SWEEPABLE, help_text

    assert all(f.metadata.get("group") in SECTIONS for k, f in FIELDS.items() if "." not in k)
    assert GROUPS == ("ppo", "sac", "coherent", "coherent_sac", "noisynet", "psne", "gsde", "pink", "lattice")
    text = help_text()
    titles = [*SECTIONS, *(f"{g}.*" for g in GROUPS)]
    headers = [text.index(f"\n{t}") for t in titles]
    assert headers == sorted(headers)
    # Each option sits under its own section's or group's header.
    for key, f in FIELDS.items():
        pos = text.index(f"\n  {key}=")
        title = max((h, t) for h, t in zip(headers, titles, strict=True) if h < pos)[1]
        assert title == (f"{key.split('.')[0]}.*" if "." in key else f.metadata["group"]), key
    assert "sweepable" in text and all(k in text for k in SWEEPABLE)

"""The config's groups: JAX-free import, the flat keys of before, every stored config.yaml."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers import child_env

from coherent_jax.config import (
    FIELDS,
    LEGACY_KEYS,
    ConfigError,
    flat_dict,
    get_value,
    modern_key,
    parse_overrides,
)
from coherent_jax.run.checkpoint import load_config, write_config

ROOT = Path(__file__).resolve().parents[1]
STORED = sorted((ROOT / "experiments" / "results").rglob("config.yaml"))


def test_config_imports_without_jax():
    code = "import sys, coherent_jax.config; assert 'jax' not in sys.modules, sorted(sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


# A value of each moved setting that differs from its default and passes its checks.
_LEGACY_VALUES = {
    "num_minibatches": "4",
    "vf_lr": "0.001",
    "vf_iters": "3",
    "update_after": "7",
    "target_entropy": "-2.0",
    "coherent_inference": "filter",
    "sigma_alpha": "1.5",
    "gsde_resample_every": "9",
    "pink_exponent": "2.0",
    "num_epochs": "3",
    "buffer_size": "5000",
    "batch_size": "64",
    "warmup_steps": "100",
}


@pytest.mark.parametrize("old", sorted(LEGACY_KEYS))
def test_flat_key_of_before_sets_its_group_key_with_a_note(old, capsys):
    new = LEGACY_KEYS[old]
    default = get_value(parse_overrides([]), new)
    text = _LEGACY_VALUES.get(old) or (
        str(not default).lower() if isinstance(default, bool) else str(round(default * 0.5 + 0.01, 4))
    )
    extra = ["ppo.vf_lr=0.001"] if old == "vf_iters" else ["ppo.vf_iters=2"] if old == "vf_lr" else []
    from coherent_jax.config import parse

    parse._NOTED.discard(old)
    flat = parse_overrides([*extra, f"{old}={text}"])
    err = capsys.readouterr().err
    assert f"'{old}'" in err and f"'{new}'" in err and len(err.strip().splitlines()) == 1, err
    assert flat == parse_overrides([*extra, f"{new}={text}"])
    assert get_value(flat, new) != default, (old, text)
    assert capsys.readouterr().err == ""  # the grouped key gives no note


def test_flat_and_grouped_key_together_are_refused_as_one_key_given_twice():
    from coherent_jax.config import cli

    with pytest.raises(ConfigError, match="duplicated key 'coherent.beta'"):
        cli.parse_command(["beta=0.1", "coherent.beta=0.2"], {}, command="train")


def test_flat_keys_work_in_a_sweep_and_points_keep_their_names():
    from coherent_jax.run.sweep import parse_sweep

    plan = parse_sweep(["env=pointmass", "explore=coherent", "beta=[0.01,0.1]", "clip_eps=0.1"])
    assert list(plan.axes) == ["coherent.beta"]
    assert [p.name for p in plan.points] == ["p000-beta=0.01-seed=0", "p001-beta=0.1-seed=0"]
    assert [p.cfg.coherent.beta for p in plan.points] == [0.01, 0.1]
    assert plan.base.ppo.clip_eps == 0.1


def test_a_grid_stored_with_flat_axes_reads_with_grouped_ones(tmp_path):
    from coherent_jax.run.sweep import _read_grid

    (tmp_path / "grid.json").write_text(json.dumps({"axes": {"beta": [0.0, 0.1]}, "seeds": [0, 1]}))
    assert _read_grid(tmp_path) == ({"coherent.beta": [0.0, 0.1]}, [0, 1])


def test_sac_defaults_are_recorded_resolved_in_config_yaml(tmp_path):
    cfg = parse_overrides(["env=pointmass", "algo=sac", "explore=coherent"])
    write_config(tmp_path, cfg)
    stored = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert (stored["num_envs"], stored["unroll_length"], stored["activation"]) == (8, 16, "relu")
    assert stored["coherent"]["integration"] == "mc" and stored["sac"]["buffer_size"] == 1_000_000
    assert load_config(tmp_path) == cfg


def test_a_later_group_leaves_the_flat_layout_of_before_unchanged():
    """lattice.* (no flat keys of before) enters the flat layout, and so checkpoint
    fingerprints, only where a setting differs from its default."""
    from coherent_jax.run.checkpoint import config_fingerprint

    plain = parse_overrides(["env=hopper", "explore=lattice"])
    assert "lattice" not in flat_dict(plain) and "lattice" not in flat_dict(parse_overrides([]))
    changed = parse_overrides(["env=hopper", "explore=lattice", "lattice.alpha=0.5"])
    assert flat_dict(changed)["lattice"] == {"alpha": 0.5}
    assert config_fingerprint(changed) != config_fingerprint(plain)


def test_stored_results_exist():
    assert len(STORED) > 100  # the reproduction's runs, every one with flat keys


@pytest.mark.parametrize(
    "path", STORED, ids=lambda p: str(p.parent.relative_to(ROOT / "experiments" / "results"))
)
def test_every_stored_config_loads_with_its_flat_values(path):
    """Each stored config.yaml (flat keys, written before the groups) loads, and every value
    it holds is the loaded config's under the key's new name."""
    stored = yaml.safe_load(path.read_text())
    cfg = load_config(path.parent)
    flat = flat_dict(cfg)
    for key, value in stored.items():
        if isinstance(value, dict):  # the coherent ablations, nested before too
            for sub, v in value.items():
                assert get_value(cfg, f"{key}.{sub}") == v, (key, sub)
            continue
        new = modern_key(key, note=False, pair=(cfg.algo, cfg.explore))
        assert new in FIELDS, key
        expected = "" if key == "preset" and value is None else value
        assert get_value(cfg, new) == expected, key
        assert flat[key] == expected, key

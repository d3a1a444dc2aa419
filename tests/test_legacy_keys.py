"""The keys of before: Coherent-SAC's psne.* (now coherent_sac.*) and the flat keys, all in
`coherent_jax.config.parse`; old stored configs keep their fingerprints and resume."""

import ast
from pathlib import Path

import pytest
import yaml

from coherent_jax.config import (
    FIELDS,
    CoherentSACOptions,
    ConfigError,
    PsneOptions,
    from_stored,
    get_value,
    make_config,
    parse,
    parse_overrides,
    to_dict,
)
from coherent_jax.run.checkpoint import config_fingerprint, load_config

ROOT = Path(__file__).resolve().parents[1]
COHERENT_SAC = ["env=pointmass", "algo=sac", "explore=coherent"]
NEW = {"sigma_init": "0.3", "sigma_delta": "0.2", "sigma_alpha": "1.05"}
# A tiny Coherent-SAC run, as the API takes it.
TINY = {
    "env": "pointmass",
    "algo": "sac",
    "explore": "coherent",
    "num_envs": 4,
    "unroll_length": 8,
    "episode_length": 50,
    "policy_hidden": [8],
    "value_hidden": [8],
    "sac.buffer_size": 512,
    "sac.batch_size": 16,
    "sac.warmup_steps": 32,
    "sac.utd_ratio": 0.25,
    "eval_episodes": 2,
    "eval_every": 1,
    "total_steps": 64,
    "progress": False,
    "tensorboard": False,
}


@pytest.fixture(autouse=True)
def _fresh_notes():
    parse._NOTED.clear()  # each test sees its notes, whatever ran before it
    yield


@pytest.mark.parametrize("name", sorted(NEW))
@pytest.mark.parametrize("old", ["psne.{}", "{}"])
def test_old_psne_key_of_coherent_sac_sets_its_group_with_a_note(name, old, capsys):
    old, new, value = old.format(name), f"coherent_sac.{name}", NEW[name]
    cfg = parse_overrides([*COHERENT_SAC, f"{old}={value}"])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"'{old}'" in err and f"'{new}'" in err, err
    assert cfg == parse_overrides([*COHERENT_SAC, f"{new}={value}"])
    assert capsys.readouterr().err == ""  # the new key gives no note
    assert get_value(cfg, new) == float(value) != get_value(make_config(), new)
    assert cfg.psne == PsneOptions()  # PSNE's own settings untouched


def test_every_old_psne_key_gives_the_config_and_the_hyperparameters_of_the_new_ones(capsys):
    """The whole rule through the old keys is the rule through the new ones, down to the
    train state's hyperparameters the behaviour reads (so the runs are the same, bit for bit)."""
    from coherent_jax.agents.sac import SACTrainer

    old = parse_overrides([*COHERENT_SAC, *(f"psne.{k}={v}" for k, v in NEW.items())])
    assert len(capsys.readouterr().err.strip().splitlines()) == 3
    new = parse_overrides([*COHERENT_SAC, *(f"coherent_sac.{k}={v}" for k, v in NEW.items())])
    assert old == new and old.coherent_sac == CoherentSACOptions(0.3, 0.2, 1.05)
    explore = SACTrainer(new).init_hparams().explore
    assert {k: float(getattr(explore, k)) for k in ("sigma", "sigma_delta", "sigma_alpha")} == pytest.approx(
        {"sigma": 0.3, "sigma_delta": 0.2, "sigma_alpha": 1.05}
    )


def test_old_psne_keys_work_from_the_api_the_command_line_and_a_sweep(capsys):
    from coherent_jax.config import cli
    from coherent_jax.run.sweep import parse_sweep

    want = parse_overrides([*COHERENT_SAC, "coherent_sac.sigma_delta=0.2"])
    assert make_config(env="pointmass", algo="sac", explore="coherent", psne={"sigma_delta": 0.2}) == want
    parsed = cli.parse_command([*COHERENT_SAC, "psne.sigma_delta=0.2"], {}, command="train")
    assert parsed.config == want and parsed.config_items[-1] == "coherent_sac.sigma_delta=0.2"
    plan = parse_sweep([*COHERENT_SAC, "psne.sigma_init=[0.1,0.3]"])
    assert list(plan.axes) == ["coherent_sac.sigma_init"]
    assert [p.name for p in plan.points] == ["p000-sigma_init=0.1-seed=0", "p001-sigma_init=0.3-seed=0"]
    assert [p.cfg.coherent_sac.sigma_init for p in plan.points] == [0.1, 0.3]
    assert capsys.readouterr().err.count("note: ") == 2  # one per old key, once per process
    with pytest.raises(ConfigError, match="duplicated key 'coherent_sac.sigma_init'"):
        cli.parse_command(
            [*COHERENT_SAC, "psne.sigma_init=0.2", "coherent_sac.sigma_init=0.3"], {}, command="train"
        )


@pytest.mark.parametrize("pair", [("sac", "psne"), ("ppo", "psne"), ("a2c", "psne")])
def test_psne_keys_stay_psne_s_own_for_every_other_pair(pair, capsys):
    algo, explore = pair
    cfg = parse_overrides(["env=pointmass", f"algo={algo}", f"explore={explore}", "psne.sigma_delta=0.2"])
    assert cfg.psne.sigma_delta == 0.2 and cfg.coherent_sac == CoherentSACOptions()
    assert capsys.readouterr().err == ""


def test_a_coherent_sac_grid_stored_with_psne_axes_reads_with_its_own(tmp_path):
    import json

    from coherent_jax.run.sweep import _read_grid

    (tmp_path / "grid.json").write_text(json.dumps({"axes": {"psne.sigma_init": [0.1, 0.3]}, "seeds": [0]}))
    assert _read_grid(tmp_path, ("sac", "coherent")) == ({"coherent_sac.sigma_init": [0.1, 0.3]}, [0])
    assert _read_grid(tmp_path, ("sac", "psne")) == ({"psne.sigma_init": [0.1, 0.3]}, [0])


def _stored_before(cfg) -> dict:
    """`cfg`'s config.yaml as it was written before Coherent-SAC had its group: its sigma rule
    in psne's group."""
    stored = to_dict(cfg)
    stored["psne"] = stored.pop("coherent_sac")
    return stored


# The fingerprint the code before coherent_sac.* gave the config of TINY with
# psne.sigma_init=0.3 psne.sigma_delta=0.2 psne.sigma_alpha=1.05: the one its checkpoints hold.
FINGERPRINT_BEFORE = "fe775ed6223c4b89e9929b6b87441bd206fff26bf1646c11d7ca745864ba385b"


def test_a_coherent_sac_config_stored_before_its_group_loads_with_its_fingerprint(tmp_path):
    cfg = make_config({**TINY, "coherent_sac": {k: float(v) for k, v in NEW.items()}})
    stored = _stored_before(cfg)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(stored, sort_keys=False))
    loaded = load_config(tmp_path)
    assert loaded == cfg and loaded.psne == PsneOptions()
    assert config_fingerprint(loaded) == config_fingerprint(cfg) == FINGERPRINT_BEFORE
    # The flat layout of before the groups too (every committed result's config.yaml).
    flat = parse.flat_dict(cfg)
    assert {k: flat[k] for k in NEW} == {k: float(v) for k, v in NEW.items()} and "coherent_sac" not in flat
    assert from_stored(flat) == cfg
    # A config written now, with its group, is read as it is (psne's values stay psne's).
    now = {**to_dict(cfg), "psne": {"sigma_init": 0.5, "sigma_delta": 0.1, "sigma_alpha": 1.01}}
    assert from_stored(now).psne.sigma_init == 0.5 and from_stored(now).coherent_sac == cfg.coherent_sac


@pytest.mark.slow
def test_a_run_whose_config_was_stored_before_the_group_resumes(tmp_path, capsys):
    """A tiny Coherent-SAC run; its config.yaml rewritten as before (psne's group); resumed
    with a larger budget: not refused, and it continues with its sigma rule."""
    import coherent_jax

    run = tmp_path / "run"
    cfg = make_config({**TINY, "run_dir": str(run), "coherent_sac": {k: float(v) for k, v in NEW.items()}})
    first = coherent_jax.learn(cfg)
    assert [r["iteration"] for r in first.metrics] == [1, 2]
    (run / "config.yaml").write_text(yaml.safe_dump({**_stored_before(cfg), "run_dir": str(run)}))
    resumed = coherent_jax.learn({"resume": str(run), "total_steps": 128})
    assert [r["iteration"] for r in resumed.metrics] == [1, 2, 3, 4]
    assert load_config(run).coherent_sac == CoherentSACOptions(0.3, 0.2, 1.05)
    assert "note: " not in capsys.readouterr().err  # a stored config is read silently


def _imported_names(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            names |= {(node.module or "") + ":" + a.name for a in node.names}
    return names


LEGACY_HELPERS = (
    "LEGACY_KEYS",
    "COHERENT_SAC_KEYS",
    "modern_key",
    "modern_items",
    "upgrade_stored",
    "flat_dict",
)


def test_every_key_of_before_maps_through_the_one_module():
    """The tables are `parse`'s and name keys that exist; no field declares an old key of
    its own; every module outside `config/` that renames an old key imports it from there."""
    assert parse.LEGACY_KEYS and all(new in FIELDS for new in parse.LEGACY_KEYS.values())
    assert not set(parse.LEGACY_KEYS) & set(FIELDS)  # an old key is no key now
    assert all(k in FIELDS and v in FIELDS for k, v in parse.COHERENT_SAC_KEYS.items())
    assert all(len(f.metadata) and "old" not in f.metadata for f in FIELDS.values())
    for old, new in parse.LEGACY_KEYS.items():
        assert parse.modern_key(old, note=False) == new
    users = []
    for path in [*ROOT.glob("coherent_jax/**/*.py"), *ROOT.glob("experiments/*.py")]:
        if "config" in path.relative_to(ROOT).parts[:2]:
            continue
        for name in _imported_names(path):
            module, _, helper = name.partition(":")
            if helper in LEGACY_HELPERS:
                assert module == "coherent_jax.config.parse", (path, name)
                users.append(path.name)
    assert {"sweep.py", "checkpoint.py", "cell.py", "verify.py"} <= set(users)

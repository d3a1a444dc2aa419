"""The deprecated names (docs/api.md, "Deprecated names"; `coherent_jax.compat`): each answers
with its successor's object, warns once naming it and the release that removes it, and the
docs' table lists every one; ``coherent_jax.train(config)`` trains through ``learn`` while
``python -m coherent_jax.train`` stays the command line."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from helpers import child_env

import coherent_jax
from coherent_jax import compat
from coherent_jax.config import ConfigError, make_config

ROOT = Path(__file__).resolve().parents[1]

#: former dotted name -> the dotted name now (the docs' table, row by row).
FORMER = {
    "coherent_jax.TrainedPolicy": "coherent_jax.policy.trained.Policy",
    "coherent_jax.policy.TrainedPolicy": "coherent_jax.policy.trained.Policy",
    "coherent_jax.PolicyFunction": "coherent_jax.policy.trained.Policy",
    "coherent_jax.api.PolicyFunction": "coherent_jax.policy.trained.Policy",
    "coherent_jax.runs.CheckpointError": "coherent_jax.run.checkpoint.CheckpointError",
    "coherent_jax.tracking.TrackingError": "coherent_jax.run.outputs.TrackingError",
    "coherent_jax.divergence.DivergenceError": "coherent_jax.run.loop.DivergenceError",
    "coherent_jax.presets.PRESETS": "coherent_jax.config.schema.PRESETS",
    "coherent_jax.config.presets.PRESETS": "coherent_jax.config.schema.PRESETS",
    "coherent_jax.run.policy.Policy": "coherent_jax.policy.net.PolicyNet",
    "coherent_jax.run.policy.load_policy": "coherent_jax.policy.net.read_policy",
    "coherent_jax.run.policy.PolicyError": "coherent_jax.policy.net.PolicyError",
    "coherent_jax.evaluate.gymnasium_returns": "coherent_jax.run.evaluation.gymnasium_returns",
}
MOVED = ("coherent_jax.runs", "coherent_jax.tracking", "coherent_jax.divergence", "coherent_jax.presets")
MOVED += ("coherent_jax.config.presets", "coherent_jax.run.policy")


@pytest.fixture(autouse=True)
def fresh(monkeypatch):
    """Each test starts as a new process would: nothing warned yet, no former module imported."""
    monkeypatch.setattr(compat, "_warned", set())
    for name in MOVED:
        monkeypatch.delitem(sys.modules, name, raising=False)
        parent, _, attr = name.rpartition(".")
        module = sys.modules.get(parent)
        if module is not None and attr in vars(module):
            monkeypatch.delattr(module, attr)


def _deprecations(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, DeprecationWarning)]


@pytest.mark.parametrize("old", FORMER)
def test_a_former_name_is_its_successor_and_warns_once(old):
    new = FORMER[old]
    with pytest.warns(DeprecationWarning) as record:
        got = compat.resolve(old)
    assert got is compat.resolve(new)
    messages = _deprecations(record)
    subjects = [m.split(" is deprecated: use ")[0] for m in messages]
    assert subjects[-1] == old or (len(subjects) == 1 and f"{subjects[0]}." in old), messages
    assert len(set(subjects)) == len(subjects) <= 2, messages  # a renamed name of a moved module: both
    assert all(m.endswith(f"(removed in coherent_jax {compat.REMOVED_IN})") for m in messages)
    assert all(" is deprecated: use coherent_jax." in m for m in messages)
    with warnings.catch_warnings(record=True) as again:
        warnings.simplefilter("always")
        assert compat.resolve(old) is got
    assert not _deprecations(again)  # once per process


def test_a_moved_module_imports_in_every_form():
    with pytest.warns(
        DeprecationWarning, match=r"^coherent_jax\.runs is deprecated: use coherent_jax\.run\.checkpoint "
    ):
        from coherent_jax.runs import CheckpointError  # the import is what is tested
    from coherent_jax.run.checkpoint import CheckpointError as now

    assert CheckpointError is now
    runs = importlib.import_module("coherent_jax.runs")
    assert (
        coherent_jax.runs is runs
        and runs.load_config is importlib.import_module("coherent_jax.run.checkpoint").load_config
    )
    with pytest.warns(DeprecationWarning, match=r"coherent_jax\.run\.policy\.Policy .*PolicyNet"):
        from coherent_jax.run.policy import Policy
    assert Policy.__name__ == "PolicyNet"
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("coherent_jax.runs.deeper")
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        coherent_jax.no_such_name  # noqa: B018
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("coherent_jax.never_was")


def test_config_from_overrides_is_make_config():
    with pytest.warns(
        DeprecationWarning, match=r"Config\.from_overrides is deprecated: use coherent_jax\.make_config"
    ):
        cfg = coherent_jax.Config.from_overrides({"env": "pointmass"}, seed=3)
    assert cfg == make_config({"env": "pointmass"}, seed=3)


def test_calling_the_train_module_is_learn(monkeypatch):
    calls = []
    monkeypatch.setattr(
        coherent_jax, "learn", lambda config, callbacks: calls.append((config, callbacks)) or "done"
    )
    module = importlib.import_module("coherent_jax.train")  # binds the module on the package
    assert coherent_jax.train is module
    with pytest.warns(
        DeprecationWarning, match=r"coherent_jax\.train\(config\) is deprecated: use coherent_jax\.learn"
    ):
        assert coherent_jax.train({"env": "pointmass"}) == "done"
    assert coherent_jax.train({"seed": 1}, callbacks=["cb"]) == "done"
    assert calls == [({"env": "pointmass"}, None), ({"seed": 1}, ["cb"])]
    assert callable(coherent_jax.train.main)  # still the command line's module


def test_calling_the_train_module_refuses_as_learn_does(tmp_path):
    with (
        pytest.warns(DeprecationWarning),
        pytest.raises(ConfigError, match=r"^invalid value for 'lr': -1\.0"),
    ):
        coherent_jax.train({"lr": -1.0, "run_dir": str(tmp_path / "run")})
    assert list(tmp_path.iterdir()) == []


def test_a_script_sees_the_warning_once_at_its_own_line():
    """Run as ``__main__`` (Python's default filters show DeprecationWarning there), without
    loading JAX for the config's former name."""
    code = (
        "import sys, coherent_jax\n"
        "cfg = coherent_jax.Config.from_overrides(env='pointmass')\n"
        "cfg = coherent_jax.Config.from_overrides(env='pointmass')\n"
        "from coherent_jax.presets import PRESETS\n"
        "assert 'jax' not in sys.modules and PRESETS\n"
    )
    out = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stderr.splitlines() if "DeprecationWarning" in line]
    assert [line.split(": DeprecationWarning")[0] for line in lines] == ["<string>:2", "<string>:4"], (
        out.stderr
    )


def test_the_docs_table_lists_every_former_name_and_its_release():
    text = (ROOT / "docs" / "api.md").read_text()
    table = text.split("\n## Deprecated names\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    assert rows and all(line.rstrip().endswith(f"| {compat.REMOVED_IN} |") for line in rows)
    listed = " ".join(rows)
    for old in [*FORMER, "coherent_jax.Config.from_overrides", "coherent_jax.train(config)"]:
        module, _, name = old.rpartition(".")
        assert old in listed or (module in MOVED and module in listed and name in listed), old
    assert not re.search(
        r"\bTrainedPolicy\b|\bPolicyFunction\b", text.split("\n## Every public name\n")[1].split("\n## ")[0]
    )

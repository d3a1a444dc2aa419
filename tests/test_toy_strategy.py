"""Adding a strategy is its module, one registry row, its settings group and its tests
(docs/strategies.md, "Adding a strategy"): a toy strategy added to a copy of the package in
those places only is chosen by ``explore=toy``, reads its own setting, trains an
iteration, and is refused with a bad setting or an algorithm it refuses."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import ROOT, child_env

TOY_MODULE = '''"""A toy strategy: Gaussian action noise whose initial std is its own setting."""

from coherent_jax.exploration.action import ActionNoise


class ToyNoise(ActionNoise):
    name = "toy"

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.policy_hidden, cfg.activation, cfg.toy.init_std)
'''

TOY_GROUP = '''

@dataclasses.dataclass
class ToyOptions(Group):
    """The toy strategy's setting, ``toy.<key>=value``."""

    init_std: float = field(0.25, "initial std", check=(lambda v: number(v) and v > 0, "a number > 0"))
'''

# (file of the package, text after which the toy's line goes, the line).
EDITS = (
    (
        "agents/registry.py",
        'Registered("lattice", Lattice, LatticeBehaviour),\n',
        '    Registered("toy", ToyNoise, None),\n',
    ),
    (
        "agents/registry.py",
        "from coherent_jax.exploration.action import ActionNoise\n",
        "from coherent_jax.exploration.toy import ToyNoise\n",
    ),
    ("strategies.py", '    Strategy("lattice"),\n', '    Strategy("toy", refused={"sac": "a toy"}),\n'),
    (
        "config/schema.py",
        '_group(LatticeOptions, "explore=lattice")\n',
        '    toy: ToyOptions = _group(ToyOptions, "explore=toy")\n',
    ),
    ("config/schema.py", "from coherent_jax.config.groups import (\n", "    ToyOptions,\n"),
)

SCRIPT = """
import json
import jax
import numpy as np
from coherent_jax.agents import make_trainer
from coherent_jax.config import ConfigError, parse_overrides

small = ["env=pointmass", "num_envs=4", "unroll_length=8", "episode_length=16", "ppo.num_epochs=1",
         "ppo.num_minibatches=1", "policy_hidden=[8]", "value_hidden=[8]", "eval_episodes=2"]
cfg = parse_overrides([*small, "explore=toy", "toy.init_std=0.3"])
trainer = make_trainer(cfg)
state = jax.jit(trainer.init)(jax.random.PRNGKey(0))
state, metrics = jax.jit(trainer.iteration)(state)
refusals = []
for bad in (["toy.init_std=-1"], ["algo=sac"]):
    try:
        parse_overrides([*small, "explore=toy", *bad])
    except ConfigError as exc:
        refusals.append(str(exc))
scalars = {k: float(v) for k, v in jax.device_get(metrics).items() if np.ndim(v) == 0}
print(json.dumps({"strategy": type(trainer.strategy).__name__, "init_std": trainer.strategy.init_std,
                  "action_std": [v for k, v in scalars.items() if k.endswith("action_std")],
                  "losses": {k: v for k, v in scalars.items() if "loss" in k}, "refusals": refusals}))
"""


def add_toy(package: Path) -> set[str]:
    """Adds the toy strategy to the package copy at ``package``; returns the files it touched."""
    (package / "exploration" / "toy.py").write_text(TOY_MODULE)
    touched = {"exploration/toy.py"}
    groups = package / "config" / "groups.py"
    groups.write_text(groups.read_text() + TOY_GROUP)
    touched.add("config/groups.py")
    for name, anchor, line in EDITS:
        path = package / name
        text = path.read_text()
        assert text.count(anchor) == 1, (name, anchor)
        path.write_text(text.replace(anchor, anchor + line))
        touched.add(name)
    return touched


@pytest.mark.slow  # a subprocess compiles and trains: about 2 minutes on a loaded 2-core machine
def test_a_toy_strategy_added_in_the_four_places_trains(tmp_path):
    copy = tmp_path / "repo"
    shutil.copytree(
        ROOT / "coherent_jax", copy / "coherent_jax", ignore=shutil.ignore_patterns("__pycache__")
    )
    touched = add_toy(copy / "coherent_jax")
    # Its module; its registry row and its name in the JAX-free list; its settings group.
    assert touched == {
        "exploration/toy.py",
        "agents/registry.py",
        "strategies.py",
        "config/groups.py",
        "config/schema.py",
    }
    env = child_env()
    env["PYTHONPATH"] = str(copy) + os.pathsep + env["PYTHONPATH"]
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["strategy"] == "ToyNoise" and out["init_std"] == 0.3
    (action_std,) = out["action_std"]  # its own setting, after one update
    assert abs(action_std - 0.3) < 0.05
    assert out["losses"] and all(math.isfinite(v) for v in out["losses"].values()), out["losses"]
    bad_std, bad_algo = out["refusals"]
    assert "toy.init_std" in bad_std and "> 0" in bad_std
    assert "a toy" in bad_algo

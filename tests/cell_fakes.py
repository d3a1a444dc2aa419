"""A cell's files laid out as a study's sweeps write them, for the tests of the suites, their
carried state and their report; and the one loaded reproduce module they share (report.py
imports it by name)."""

import json

from helpers import load_experiment

from coherent_jax.study.cell import cell_dir

reproduce = load_experiment("reproduce")


def fake_sweep(cell, results, finished):
    """The cell's directory in its suite's folder under `results` (``results/SUITE/CELL``)."""
    d = cell_dir(cell, results / cell.suite)
    point = d / "sweep" / "seed=0"
    point.mkdir(parents=True)
    (point / "config.yaml").write_text("seed: 0\n")
    total = int(cell.setting("total_steps"))
    rows = [{"iteration": 1, "env_steps": total // 4}, {"iteration": 2, "env_steps": total // 2}]
    (point / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (d / "cell.json").write_text(json.dumps({"spec": cell.spec(), "fingerprint": cell.fingerprint}))
    if finished:
        (d / "sweep" / "sweep.json").write_text(json.dumps({"sweep_env_steps_per_s": 1000.0}))
    return d

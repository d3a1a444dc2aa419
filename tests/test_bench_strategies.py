"""The strategies benchmark: every strategy's real iteration timed side by side."""

import json

import pytest
from helpers import TINY_BENCH, TINY_BENCH_SAC

from benchmarks import strategies
from coherent_jax.strategies import SUPPORTED_ALGOS


def test_all_means_every_strategy_the_algorithm_runs_with_action_first():
    for algo in ("ppo", "sac"):
        names = strategies.parse([f"algo={algo}"]).settings["strategies"]
        assert names[0] == "action"
        assert names == [s for s in SUPPORTED_ALGOS if algo in SUPPORTED_ALGOS[s]]
    assert "noisynet" not in strategies.parse(["algo=sac"]).settings["strategies"]
    # A list keeps its order: its first entry is the baseline.
    assert strategies.parse(["strategies=[gsde,lattice]"]).settings["strategies"] == ["gsde", "lattice"]


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_tiny_run_times_each_strategy_against_the_first(tmp_path, algo):
    out = tmp_path / "strategies.json"
    sizes = TINY_BENCH_SAC if algo == "sac" else ("ppo.num_minibatches=2",)
    items = [f"algo={algo}", *TINY_BENCH, *sizes, "strategies=[gsde,lattice]", "iterations=3", f"out={out}"]
    result = strategies.run(items, log=lambda msg: None)
    saved = json.loads(out.read_text())
    tr = saved["training"]
    assert tr["baseline"] == "gsde" and list(tr["rows"]) == ["gsde", "lattice"]
    assert saved["settings"]["config"]["explore"] == "action"  # the suite varies it per row
    if algo == "sac":
        assert saved["settings"]["config"]["sac"]["warmup_steps"] != 0  # the default, recorded as given
    for e in tr["rows"].values():
        assert len(e["iteration_s"]) == 3 and e["compile_s"] > 0
        assert e["iteration_s_median"] == pytest.approx(sorted(e["iteration_s"])[1])
        assert e["env_steps_per_s"] == pytest.approx(32 / e["iteration_s_median"])
        expected_updates = 8 if algo == "sac" else 10 * 2  # utd 0.25 x 32 steps; epochs x minibatches
        assert e["updates_applied"] == [expected_updates] * 3
    ratio = tr["rows"]["lattice"]["iteration_s_median"] / tr["rows"]["gsde"]["iteration_s_median"]
    assert tr["rows"]["lattice"]["time_over_baseline"] == pytest.approx(ratio)
    assert tr["rows"]["gsde"]["time_over_baseline"] == 1.0
    table = strategies.format_table(result)
    assert "lattice" in table and "time relative to gsde" in table

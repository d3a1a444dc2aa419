"""The SAC benchmark: bad settings refused up front; a tiny real run writes consistent figures."""

import json

import pytest
from helpers import TINY_BENCH, TINY_BENCH_SAC

from benchmarks import sac
from coherent_jax.config import ConfigError


@pytest.mark.parametrize(
    "args,key",
    [
        (["explore=coherent"], "'explore'"),
        (["iterations=0"], "'iterations'"),
        (["bogus=1"], "'bogus'"),
        (["coherent.integration=analytic"], "'coherent.integration'"),
    ],
)
def test_bad_settings_exit_2_and_write_nothing(tmp_path, capsys, args, key):
    from benchmarks.__main__ import main

    assert main(["sac", *args, f"out={tmp_path / 'r.json'}"]) == 2
    err = capsys.readouterr().err
    assert key in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_tiny_run_reports_both_strategies(tmp_path):
    out = tmp_path / "sac.json"
    overrides = [*TINY_BENCH, *TINY_BENCH_SAC, "iterations=2", f"out={out}"]
    result = sac.run(overrides, log=lambda msg: None)
    saved = json.loads(out.read_text())
    tr = saved["training"]
    assert tr["env_steps_per_iteration"] == 32 and tr["updates_per_iteration"] == 8
    for name in ("action", "coherent"):
        e = tr[name]
        assert len(e["iteration_s"]) == 2 and e["compile_s"] > 0
        assert e["env_steps_per_s"] == pytest.approx(32 / e["iteration_s_median"])
        assert e["gradient_updates_per_s"] == pytest.approx(8 / e["iteration_s_median"])
    assert "Coherent-SAC / SAC" in sac.format_table(result)
    with pytest.raises(ConfigError):
        sac.run(["algo=ppo"])

"""``python -m coherent_jax.plot``: curves and aggregates from run directories, checked by hand."""

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from coherent_jax.config import parse_overrides, to_dict
from coherent_jax.plot import aggregate_iqm, main, mean_and_interval, normalized_final_scores

STEPS = [100, 200, 300, 400]


def write_run(root, env, explore, seed, finals_offset):
    """A run directory with a synthetic learning curve (eval rows every 2nd iteration)."""
    cfg = parse_overrides([f"env={env}", f"explore={explore}", f"seed={seed}"])
    path = root / f"{env}-{explore}-s{seed}"
    path.mkdir(parents=True)
    (path / "config.yaml").write_text(OmegaConf.to_yaml(to_dict(cfg)))
    rows = []
    for i, s in enumerate(STEPS, start=1):
        row = {"iteration": i, "env_steps": s, "time_s": 0.1 * i, "train/episode_return": float(i)}
        if i % 2 == 0:
            row["eval/episode_return"] = finals_offset + 10.0 * i + seed
        rows.append(row)
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_t_interval_matches_a_hand_computation():
    curves = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 2.0]])
    mean, half = mean_and_interval(curves)
    # n = 3: t_{0.975, 2} = 4.302653, sample std of (1, 3, 5) = 2.
    np.testing.assert_allclose(mean, [3.0, 2.0])
    np.testing.assert_allclose(half, [4.302653 * 2 / np.sqrt(3), 0.0], rtol=1e-6)
    assert mean_and_interval(curves[:1])[1].tolist() == [0.0, 0.0]


def test_iqm_and_bootstrap_interval_match_hand_computation():
    # 4 runs x 2 tasks = 8 scores 1..8: the middle half is 3, 4, 5, 6, IQM 4.5.
    scores = {"a": np.array([[1.0, 5.0], [2.0, 6.0], [3.0, 7.0], [4.0, 8.0]])}
    r = aggregate_iqm(scores, reps=500, seed=0)["a"]
    assert r["iqm"] == pytest.approx(4.5)
    assert 1.0 <= r["ci_low"] < 4.5 < r["ci_high"] <= 8.0
    # Stratified: each resample keeps 4 scores of task 0 (from 1-4) and 4 of task 1 (5-8),
    # so no resample can have an IQM below the IQM of (1,1,1,1,5,5,5,5) = 3.
    assert r["ci_low"] >= 3.0


def test_normalisation_is_min_max_per_task(tmp_path):
    from coherent_jax.plot import load_run

    runs = [
        load_run(write_run(tmp_path, env, ex, seed, off), "eval/episode_return")
        for env, ex, seed, off in [
            ("hopper", "action", 0, 0.0),
            ("hopper", "coherent", 0, 100.0),
            ("hopper", "coherent", 1, 100.0),
            ("ant", "action", 0, 0.0),
            ("ant", "coherent", 0, -50.0),
        ]
    ]
    scores, norm = normalized_final_scores(runs)
    assert norm["tasks"] == ["ant", "hopper"]
    assert norm["bounds"]["hopper"] == (40.0, 141.0)  # finals 40, 140, 141
    np.testing.assert_allclose(scores["action"], [[1.0, 0.0]])
    np.testing.assert_allclose(scores["coherent"], [[0.0, 100 / 101]])  # one seed on ant limits to one row


def png_pixels(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)


def test_cli_writes_non_blank_curves_and_aggregate(tmp_path, capsys):
    runs = tmp_path / "runs"
    for env in ("hopper", "ant"):
        for explore, off in (("action", 0.0), ("coherent", 30.0)):
            for seed in range(3):
                write_run(runs, env, explore, seed, off)
    out = tmp_path / "plots"
    assert main([str(runs), f"out={out}", "reps=300"]) == 0
    text = capsys.readouterr().out
    assert "12 runs, 2 task(s)" in text
    # hopper/action: finals 40 + seed, mean 41, interval t_{0.975,2} * 1 / sqrt(3).
    assert f"41.00 +- {4.302653 / np.sqrt(3):.2f}" in text
    pixels = png_pixels(out / "learning_curves.png")
    assert pixels.shape[0] > 100 and pixels.std() > 10.0
    assert png_pixels(out / "aggregate.png").std() > 10.0
    report = json.loads((out / "aggregate.json").read_text())
    # Per task, finals are 40, 41, 42 (action) and 70, 71, 72 (coherent), normalised by (x - 40) / 32.
    # Action's 6 scores are (0, 0, 1, 1, 2, 2) / 32; the IQM drops int(0.25 * 6) = 1 at each end:
    # mean(0, 1, 1, 2) / 32. Coherent's: mean(30, 31, 31, 32) / 32.
    expected = {"action": 1.0 / 32, "coherent": 31.0 / 32}
    for name, value in expected.items():
        assert report["iqm"][name]["iqm"] == pytest.approx(value)


@pytest.mark.parametrize(
    "args,text",
    [
        ([], "at least one run directory"),
        (["{tmp}/nowhere"], "not a directory"),
        (["{tmp}/empty"], "config.yaml"),
        (["{run}", "colour=red"], "'colour'"),
        (["{run}", "reps=abc"], "'reps'"),
        (["{run}", "metric=eval/nothing"], "'eval/nothing'"),
    ],
)
def test_bad_input_is_refused_and_writes_nothing(tmp_path, capsys, args, text):
    run = write_run(tmp_path, "hopper", "action", 0, 0.0)
    (tmp_path / "empty").mkdir()
    args = [a.format(tmp=tmp_path, run=run) for a in args]
    assert main([*args, f"out={tmp_path / 'plots'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and text in err[0], err
    assert not (tmp_path / "plots").exists()

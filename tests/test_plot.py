"""``python -m coherent_jax.plot``: curves and aggregates from run directories, checked by hand."""

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from coherent_jax.config import parse_overrides, to_dict
from coherent_jax.plot import (
    aggregate_iqm,
    load_run,
    main,
    mean_and_interval,
    normalized_final_scores,
    stratified_bootstrap,
)

STEPS = [100, 200, 300, 400]


def write_run(root, env, explore, seed, finals_offset, extra=(), steps=STEPS, name=None):
    """A run directory with a synthetic learning curve (eval rows every 2nd iteration)."""
    cfg = parse_overrides([f"env={env}", f"explore={explore}", f"seed={seed}", *extra])
    path = root / (name or f"{env}-{explore}-s{seed}")
    path.mkdir(parents=True)
    (path / "config.yaml").write_text(OmegaConf.to_yaml(to_dict(cfg)))
    rows = []
    for i, s in enumerate(steps, start=1):
        row = {"iteration": i, "env_steps": s, "time_s": 0.1 * i, "train/episode_return": float(i)}
        if i % 2 == 0:
            row["eval/episode_return"] = finals_offset + 10.0 * i + seed
        rows.append(row)
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_bootstrap_interval_of_the_mean_stays_in_the_data():
    """With 2 or 3 seeds the 95% percentile bootstrap of the mean is the seeds' range (each
    extreme resample has probability 1/n^(n-1) > 2.5%), where a t-interval is far wider;
    with 10 seeds it is close to the normal interval mean +- 1.96 s / sqrt(n)."""
    curves = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 2.0]])
    mean, low, high = mean_and_interval(curves)
    np.testing.assert_allclose(mean, [3.0, 2.0])
    np.testing.assert_allclose(low, [1.0, 2.0])
    np.testing.assert_allclose(high, [5.0, 2.0])
    mean, low, high = mean_and_interval(np.array([[0.0], [10.0]]))
    assert (low[0], mean[0], high[0]) == (0.0, 5.0, 10.0)  # t-interval: 5 +- 63.5
    assert mean_and_interval(curves[:1])[1].tolist() == [1.0, 2.0]
    ten = np.random.default_rng(1).normal(0.0, 1.0, size=(10, 1))
    mean, low, high = mean_and_interval(ten, reps=20000)
    half = 1.96 * ten.std() / np.sqrt(10)  # the bootstrap's plug-in std (ddof 0)
    assert (high - low)[0] == pytest.approx(2 * half, rel=0.1)
    assert ten.min() < low[0] < mean[0] < high[0] < ten.max()
    again = mean_and_interval(ten, reps=20000)
    np.testing.assert_array_equal(again[1], low)  # seeded: the same band every time


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


def test_settings_that_change_only_with_the_task_split_no_group(tmp_path):
    """Per-task settings (reward scaling on hopper alone) are not in the labels, so the
    aggregate pairs each strategy across tasks; a setting that varies on one task is."""
    scaled = ["ppo.normalize_rewards=true"]
    runs = [
        load_run(write_run(tmp_path, env, ex, 0, off, extra, name=name), "eval/episode_return")
        for env, ex, off, extra, name in [
            ("hopper", "action", 0.0, scaled, "h-a"),
            ("hopper", "coherent", 100.0, scaled, "h-c"),
            ("ant", "action", 0.0, [], "a-a"),
            ("ant", "coherent", -50.0, [], "a-c"),
        ]
    ]
    scores, _ = normalized_final_scores(runs)
    assert sorted(scores) == ["action", "coherent"]
    np.testing.assert_allclose(scores["action"], [[1.0, 0.0]])
    # The same key varying within one task labels every group on every task.
    other = write_run(tmp_path, "ant", "coherent", 0, 0.0, scaled, name="a-c2")
    runs.append(load_run(other, "eval/episode_return"))
    scores, _ = normalized_final_scores(runs)
    assert "coherent ppo.normalize_rewards=True" in scores
    assert "coherent ppo.normalize_rewards=False" not in scores


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
    # hopper/action: finals 40 + seed, mean 41; with 3 seeds the bootstrap interval is their range.
    assert "n=3  eval/episode_return at 400 steps: 41.00, 95% bootstrap CI [40.00, 42.00]" in text
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
        (["{run}", "reps=10"], "'reps'"),
        (["{run}", "out={tmp}/a_file/plots"], "'out'"),
    ],
)
def test_bad_input_is_refused_and_writes_nothing(tmp_path, capsys, args, text):
    run = write_run(tmp_path, "hopper", "action", 0, 0.0)
    (tmp_path / "empty").mkdir()
    (tmp_path / "a_file").write_text("")
    args = [a.format(tmp=tmp_path, run=run) for a in args]
    assert main([*args, f"out={tmp_path / 'plots'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and text in err[0], err
    assert not (tmp_path / "plots").exists()


def test_runs_differing_in_more_than_the_seed_are_not_averaged(tmp_path, capsys):
    """Two betas are two lines, labelled by beta; seeds of one beta are one line."""
    from coherent_jax.plot import group_curves

    runs = tmp_path / "runs"
    for beta, off in (("0.01", 0.0), ("0.1", 100.0)):
        for seed in (0, 1):
            write_run(
                runs, "hopper", "coherent", seed, off, [f"coherent.beta={beta}"], name=f"b{beta}-s{seed}"
            )
    loaded = [load_run(p, "eval/episode_return") for p in sorted(runs.iterdir())]
    grouped = group_curves(loaded)["hopper"]
    assert sorted(grouped) == ["coherent.beta=0.01", "coherent.beta=0.1"]
    assert grouped["coherent.beta=0.1"].values[:, -1].tolist() == [140.0, 141.0]
    # run_dir, progress and the seed do not split a group.
    write_run(
        runs, "hopper", "coherent", 2, 0.0, ["coherent.beta=0.01", "progress=false", "run_dir=x"], name="b-s2"
    )
    assert main([str(runs), f"out={tmp_path / 'plots'}", "reps=200"]) == 0
    text = capsys.readouterr().out
    assert "coherent.beta=0.01" in text and "n=3" in text and "coherent.beta=0.1" in text and "n=2" in text


def test_seeds_logged_at_different_steps(tmp_path, capsys):
    """Offset evaluation steps are interpolated where all seeds cover; disjoint ones drawn one by one."""
    from coherent_jax.plot import common_curves

    a = write_run(tmp_path / "r", "hopper", "action", 0, 0.0, steps=[100, 200, 300, 400])  # eval 200, 400
    b = write_run(tmp_path / "r", "hopper", "action", 1, 0.0, steps=[150, 300, 450, 600])  # eval 300, 600
    c = common_curves([load_run(p, "eval/episode_return") for p in (a, b)])
    # Shared range [300, 400]; seed 0 is 20 at 200 and 40 at 400, seed 1 is 21 at 300 and 41 at 600.
    assert c.steps.tolist() == [300, 400] and c.interpolated
    np.testing.assert_allclose(c.values, [[30.0, 40.0], [21.0, 21.0 + 20.0 * 100 / 300]])
    out = tmp_path / "plots"
    assert main([str(tmp_path / "r"), f"out={out}", "reps=200"]) == 0
    assert "interpolated" in capsys.readouterr().out
    assert png_pixels(out / "learning_curves.png").std() > 10.0

    d = write_run(tmp_path / "d", "hopper", "action", 0, 0.0, steps=[100, 200])
    e = write_run(tmp_path / "d", "hopper", "action", 1, 0.0, steps=[300, 400])
    assert common_curves([load_run(p, "eval/episode_return") for p in (d, e)]).steps.size == 0
    assert main([str(tmp_path / "d"), f"out={out}", "reps=200"]) == 0
    assert "drawn one by one" in capsys.readouterr().out


def test_sweep_point_directories_with_equals_in_their_names(tmp_path, capsys):
    sweep = tmp_path / "sweep-hopper"
    for i, seed in enumerate((0, 1)):
        write_run(
            sweep, "hopper", "coherent", seed, 0.0, ["coherent.beta=0.1"], name=f"p00{i}-beta=0.1-seed={seed}"
        )
    (sweep / "sweep.csv").write_text("beta,mean\n")
    point = sweep / "p000-beta=0.1-seed=0"
    assert main([str(sweep), f"out={tmp_path / 'a'}", "reps=200"]) == 0
    assert "n=2" in capsys.readouterr().out
    assert main([str(point), f"out={tmp_path / 'b'}", "reps=200"]) == 0
    assert "n=1" in capsys.readouterr().out


def test_stratified_bootstrap_is_seeded_and_resamples_within_each_task():
    """The same seed gives the same interval; resamples never mix tasks; with one array
    per side each is resampled on its own (a constant array keeps a zero-width interval)."""
    rng = np.random.default_rng(3)
    x = np.stack([rng.normal(0.0, 1.0, 7), rng.normal(100.0, 1.0, 7)], axis=1)  # [runs, tasks]
    column_means = lambda a: a.mean(axis=0)  # noqa: E731
    first = stratified_bootstrap([x], column_means, 500, 0)
    again = stratified_bootstrap([x], column_means, 500, 0)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
    point, low, high = first
    np.testing.assert_allclose(point, x.mean(axis=0))
    assert np.all(low < point) and np.all(point < high)
    assert x[:, 0].min() <= low[0] and high[0] <= x[:, 0].max()  # task 0 never sees task 1's runs
    assert x[:, 1].min() <= low[1] and high[1] <= x[:, 1].max()
    other = stratified_bootstrap([x], column_means, 500, 1)
    assert not np.array_equal(other[1], low)
    const = np.full((4, 2), 2.0)
    _, lo, hi = stratified_bootstrap([x, const], lambda a, b: np.array([b.mean()]), 200, 0)
    assert lo[0] == hi[0] == 2.0

"""experiments/reproduce.py: suites, cell selection, refusals and the state of a cell.

These checks need no training: cells are read from the suite tables, and a cell's
state is read from files laid out as a sweep writes them.
"""

import json
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from helpers import child_env, load_experiment

ROOT = Path(__file__).resolve().parents[1]


reproduce = load_experiment("reproduce")


def _report():
    """experiments/report.py (it imports plotting and rliable on load, so only where needed)."""
    return load_experiment("report")


def test_thesis_suite_covers_every_comparison():
    names = {c.name for c in reproduce.thesis_cells()}
    for task in ("halfcheetah", "walker2d", "hopper"):
        for algo in ("ppo", "a2c"):
            for s in ("action", "coherent", "noisynet", "psne"):
                assert f"{task}/{algo}/{s}" in names
        for s in ("action", "coherent", "psne"):
            assert f"{task}/sac/{s}" in names
    assert all(c.seeds >= 5 for c in reproduce.thesis_cells())


def test_every_cell_is_a_valid_config_with_its_tasks_settings_for_every_strategy():
    """Every full-size cell parses as a training config (as the sweep will parse it), and the
    A2C/PPO cells of a task share that task's settings whatever the strategy."""
    from coherent_jax.config import parse_overrides
    from coherent_jax.sweep import parse_sweep

    cells = [*reproduce.thesis_cells(), *reproduce.ablation_cells(), *reproduce.beyond_cells()]
    for cell in cells:
        cfg = parse_sweep([*cell.overrides, f"seeds={cell.seeds}"]).base
        task_settings = reproduce.ONPOLICY_TASK_SETTINGS.get(cfg.env, ())
        if cfg.algo == "sac":
            assert not cfg.ppo.normalize_rewards, cell.name
        else:
            assert all(item in cell.overrides for item in task_settings), cell.name
        if cfg.algo == "a2c":  # one gradient step per iteration: its own step size
            assert cfg.lr == 3e-3, cell.name
    assert parse_overrides(["env=hopper", *reproduce.ONPOLICY_TASK_SETTINGS["hopper"]]).ppo.normalize_rewards
    assert "halfcheetah" not in reproduce.ONPOLICY_TASK_SETTINGS  # the ablations' and done cells' defaults


def test_beyond_adds_lattice_onpolicy_pink_and_sac_cells_and_keeps_the_others():
    """Lattice and pink at the on-policy exponent 0.5 (a cell name of its own) for A2C and PPO,
    gSDE, pink and Lattice for SAC at the thesis suite's SAC budget; the first cells keep
    their specification (and so their stored results)."""
    cells = {c.name: c for c in reproduce.beyond_cells()}
    thesis_sac = reproduce.select("thesis", ["hopper/sac/action"])[0]
    for task in reproduce.THESIS_TASKS:
        for algo in ("ppo", "a2c"):
            assert cells[f"{task}/{algo}/lattice"].setting("explore") == "lattice"
            pink = cells[f"{task}/{algo}/pink-exp0.5"]
            assert (pink.setting("explore"), pink.setting("pink.exponent")) == ("pink", "0.5")
            assert cells[f"{task}/{algo}/pink"].setting("pink.exponent") is None
        for explore in ("gsde", "pink", "lattice"):
            sac = cells[f"{task}/sac/{explore}"]
            assert sac.overrides[3:] == thesis_sac.overrides[3:]  # total_steps and SAC's settings
    assert cells["halfcheetah/ppo/gsde"].overrides == (
        "env=halfcheetah",
        "algo=ppo",
        "explore=gsde",
        "total_steps=1000000",
    )
    assert len(cells) == len(reproduce.THESIS_TASKS) * (2 * 4 + 3)
    assert "pink-exp0.5" in reproduce.BEYOND_LABELS and "lattice" in reproduce.SPARSE_STRATEGIES


def test_sparse_suite_runs_every_strategy_on_four_sparse_control_tasks():
    from coherent_jax.config import EXPLORES, SUPPORTED_ALGOS
    from coherent_jax.envs.registry import DMC_SPARSE_TASKS

    cells = reproduce.sparse_cells()
    tasks = {c.setting("env") for c in cells}
    assert len(tasks) >= 4 and tasks <= set(DMC_SPARSE_TASKS)
    on_policy = {e for e in EXPLORES if "ppo" in SUPPORTED_ALGOS[e]}
    for task in tasks:
        mine = [c for c in cells if c.setting("env") == task]
        assert {c.setting("explore") for c in mine} == on_policy
        assert all(c.setting("algo") == "ppo" and c.seeds >= 5 for c in mine)
        (coherent,) = [c for c in mine if c.setting("explore") == "coherent"]
        assert len(coherent.setting("beta").strip("[]").split(",")) >= 3


def test_ablations_vary_one_component_each():
    from coherent_jax.config import Config

    cells = {c.name: c for c in reproduce.ablation_cells()}
    # One cell of five seeds per beta; the default beta is the thesis suite's coherent cell.
    assert reproduce.DEFAULT_BETA == Config().coherent.beta
    thesis = {c.name: c for c in reproduce.thesis_cells()}
    for algo in ("ppo", "a2c"):
        assert thesis[f"halfcheetah/{algo}/coherent"].setting("beta") is None
        betas = sorted(
            float(c.setting("beta"))
            for c in cells.values()
            if c.setting("algo") == algo and c.name.split("/")[2].startswith("coherent-beta")
        )
        assert betas == [0.0, 0.1, 0.5, 1.0]
    beta = cells["halfcheetah/ppo/coherent-beta0.5"]
    assert beta.setting("beta") == "0.5" and beta.env_steps == 5 * reproduce.ONPOLICY_STEPS
    assert cells["halfcheetah/a2c/coherent-mc"].setting("coherent.integration") == "mc"
    assert cells["halfcheetah/ppo/coherent-mc-all"].setting("coherent.layers") == "all"
    for algo in ("ppo", "a2c"):
        stored = cells[f"halfcheetah/{algo}/coherent-stored"]
        assert stored.setting("coherent.gradient") == "stored" and stored.setting("beta") is None


def test_smoke_has_one_cell_per_kind_of_cell():
    smoke = reproduce.smoke_cells()
    kinds = {reproduce.smoke_kind(c) for c in smoke}
    suites = ("thesis", "ablations", "beyond", "sparse", "protocol")
    full = [c for s in suites for c in reproduce.SUITES[s]()]
    # Pointmass in place of each task, tiny budgets: the smoke kind of a full cell keeps
    # its algorithm, strategy, override keys and grids.
    assert {reproduce.smoke_kind(c) for c in full} == kinds
    assert len(smoke) == len(kinds)
    assert all(c.setting("env") == "pointmass" for c in smoke)
    names = {c.name for c in smoke}
    assert {"pointmass/ppo/coherent-beta0", "pointmass/ppo/coherent-beta", "pointmass/sac/psne"} <= names
    assert {"pointmass/ppo/coherent-stored", "pointmass/ppo/coherent-episode"} <= names
    (grid,) = [c for c in smoke if c.name == "pointmass/ppo/coherent-beta"]
    assert grid.setting("beta").startswith("[")


def test_fingerprint_changes_with_the_specification():
    a = reproduce.Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo"), 5)
    assert a.fingerprint == reproduce.Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo"), 5).fingerprint
    assert (
        a.fingerprint
        != reproduce.Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo", "lr=1"), 5).fingerprint
    )
    assert a.fingerprint != reproduce.Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo"), 6).fingerprint


def test_selection_by_glob_and_unknown_names():
    chosen = reproduce.select("thesis", ["hopper/ppo/*"])
    assert [c.name for c in chosen] == [f"hopper/ppo/{s}" for s in ("action", "coherent", "noisynet", "psne")]
    with pytest.raises(reproduce.ReproduceError, match="unknown suite 'paper'.*allowed: smoke"):
        reproduce.select("paper", [])
    with pytest.raises(reproduce.ReproduceError, match="unknown cell 'ant/\\*'.*halfcheetah/ppo/action"):
        reproduce.select("thesis", ["ant/*"])


def _fake_sweep(cell, results, finished):
    d = reproduce.cell_dir(cell, results)
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


def test_estimates_read_cells_of_the_same_preset_and_strategy_first(tmp_path):
    """A protocol cell (``preset=thesis``: 4 envs x 1,000 steps) takes no rate from a cell
    at the defaults; a finished cell of the same strategy is taken as it ran."""
    (cell,) = reproduce.select("protocol", ["hopper/a2c/psne-thesis"])
    cost = reproduce.STRATEGY_COST
    default = cell.env_steps * cost["psne"] / reproduce.DEFAULT_RATE["a2c"]
    # The thesis suite's hopper/a2c/psne ran at the defaults: not this cell's kind.
    _fake_sweep(reproduce.select("thesis", ["hopper/a2c/psne"])[0], tmp_path, finished=True)
    assert reproduce.estimated_seconds(cell, tmp_path) == pytest.approx(default)
    # A protocol cell of the same task and algorithm, another strategy: rescaled.
    _fake_sweep(reproduce.select("protocol", ["hopper/a2c/action-thesis"])[0], tmp_path, finished=True)
    assert reproduce.estimated_seconds(cell, tmp_path) == pytest.approx(
        cell.env_steps * cost["psne"] / 1000.0
    )
    # The ablation suite's coherent cells are of the thesis suite's coherent cell's kind and
    # strategy: their rate (set to 400) is taken as it is, the action cell (1,000) left aside.
    (coherent,) = reproduce.select("thesis", ["halfcheetah/ppo/coherent"])
    _fake_sweep(reproduce.select("thesis", ["halfcheetah/ppo/action"])[0], tmp_path, finished=True)
    assert reproduce.estimated_seconds(coherent, tmp_path) == pytest.approx(
        coherent.env_steps * cost["coherent"] / 1000.0
    )
    beta0 = _fake_sweep(reproduce.select("ablations", ["halfcheetah/ppo/coherent-beta0"])[0], tmp_path, True)
    (beta0 / "sweep" / "sweep.json").write_text(json.dumps({"sweep_env_steps_per_s": 400.0}))
    assert reproduce.estimated_seconds(coherent, tmp_path) == pytest.approx(coherent.env_steps / 400.0)
    # The episode gradient is a strategy of its own cost: the coherent cell's rate (400)
    # divided by EPISODE_GRADIENT_COST, not taken as it is.
    (episode,) = reproduce.select("protocol", ["halfcheetah/ppo/coherent-episode"])
    _fake_sweep(coherent, tmp_path, finished=True)
    (reproduce.cell_dir(coherent, tmp_path) / "sweep" / "sweep.json").write_text(
        json.dumps({"sweep_env_steps_per_s": 400.0})
    )
    assert reproduce.estimated_seconds(episode, tmp_path) == pytest.approx(
        episode.env_steps * reproduce.EPISODE_GRADIENT_COST / 400.0
    )


def test_cell_states_and_compute_left(tmp_path):
    done, stopped, running, missing = reproduce.select("thesis", ["hopper/a2c/*"])
    _fake_sweep(done, tmp_path, finished=True)
    _fake_sweep(stopped, tmp_path, finished=False)
    d = _fake_sweep(running, tmp_path, finished=False)
    (d / "running.pid").write_text(f"{os.getpid()}\n")
    assert reproduce.cell_state(done, tmp_path) == "done"
    assert reproduce.cell_state(stopped, tmp_path) == "stopped"
    assert reproduce.cell_state(running, tmp_path) == "running"
    assert reproduce.cell_state(missing, tmp_path) == "missing"
    # One point of five has run half of its steps: a tenth of the cell.
    assert reproduce.progress(stopped, tmp_path)[0] == pytest.approx(0.5 / 5)
    assert reproduce.estimated_seconds(done, tmp_path) == 0.0
    # Compute left: the stopped cell's nine tenths, the missing one's all, each at the
    # finished hopper/a2c/action cell's measured 1,000 env steps/s rescaled by its
    # strategy's cost (coherent 2.5x, psne 2.2x).
    cost = reproduce.STRATEGY_COST
    assert (stopped.setting("explore"), missing.setting("explore")) == ("coherent", "psne")
    assert reproduce.estimated_seconds(stopped, tmp_path) == pytest.approx(
        0.9 * stopped.env_steps * cost["coherent"] / 1000.0
    )
    assert reproduce.estimated_seconds(missing, tmp_path) == pytest.approx(
        missing.env_steps * cost["psne"] / 1000.0
    )
    # With nothing finished of the same task and algorithm, the defaults.
    nothing = tmp_path / "nothing-run"
    default = missing.env_steps * cost["psne"] / reproduce.DEFAULT_RATE["a2c"]
    assert reproduce.estimated_seconds(missing, nothing) == pytest.approx(default)
    other = tmp_path / "other-task-run"
    _fake_sweep(reproduce.select("thesis", ["halfcheetah/a2c/action"])[0], other, finished=True)
    _fake_sweep(reproduce.select("thesis", ["hopper/ppo/action"])[0], other, finished=True)
    assert reproduce.estimated_seconds(missing, other) == pytest.approx(default)
    text = reproduce.status([done, stopped, running, missing], tmp_path)
    assert "done" in text and "stopped" in text and "running" in text and "missing" in text
    # A stale lock (its process is gone) reads as stopped.
    (d / "running.pid").write_text("999999999\n")
    assert reproduce.cell_state(running, tmp_path) == "stopped"
    # A stopped cell resumes its sweep; a missing one starts it.
    assert any(a.startswith("resume=") for a in reproduce.sweep_command(stopped, tmp_path))
    assert any(a.startswith("run_dir=") for a in reproduce.sweep_command(missing, tmp_path))


def _stopped_cell_with_a_checkpoint(cell, results):
    """A stopped cell as a SIGTERM leaves it: checkpoint, configs, logs, and what stays local."""
    d = _fake_sweep(cell, results, finished=False)
    sweep = d / "sweep"
    (sweep / "checkpoint.msgpack").write_bytes(np.random.default_rng(0).bytes(4096))
    for name in ("config.yaml", "grid.json", "versions.json", "versions-resumed-7.json"):
        (sweep / name).write_text(f"{name}\n")
    (sweep / "run.lock").write_text("123\n")
    (sweep / "seed=0" / "tb").mkdir()
    (sweep / "seed=0" / "tb" / "events.out.tfevents.1").write_bytes(b"\0" * 64)
    (d / "run.log").write_text("progress bars\n")
    return d


def test_a_stopped_cell_is_carried_by_its_packed_state_and_unpacked_whole(tmp_path):
    carry = load_experiment("carry")
    stopped, finished = reproduce.select("protocol", ["hopper/a2c/action-thesis", "hopper/a2c/psne-thesis"])
    d = _stopped_cell_with_a_checkpoint(stopped, tmp_path)
    sweep = d / "sweep"
    kept = {
        "checkpoint.msgpack", "config.yaml", "grid.json", "versions.json", "versions-resumed-7.json",
        "seed=0/config.yaml", "seed=0/metrics.jsonl",
    }  # fmt: skip
    before = {f.relative_to(sweep).as_posix(): f.read_bytes() for f in sweep.rglob("*") if f.is_file()}
    path = carry.pack(d)
    first = path.read_bytes()
    assert carry.pack(d).read_bytes() == first  # the same files, the same bytes
    fraction = reproduce.progress(stopped, tmp_path)[0]
    shutil.rmtree(sweep)  # a clone elsewhere: the carry file, no sweep directory
    assert reproduce.cell_state(stopped, tmp_path) == "carried"
    assert reproduce.progress(stopped, tmp_path)[0] == fraction == pytest.approx(0.5 / 5)
    assert "carried" in reproduce.status([stopped], tmp_path)
    assert carry.unpack(d) and not carry.unpack(d)  # once: the sweep directory is back
    after = {f.relative_to(sweep).as_posix(): f.read_bytes() for f in sweep.rglob("*") if f.is_file()}
    assert after == {k: v for k, v in before.items() if k in kept} and set(after) == kept
    assert reproduce.cell_state(stopped, tmp_path) == "stopped"
    assert any(a.startswith("resume=") for a in reproduce.sweep_command(stopped, tmp_path))
    # Refused, leaving the carry file as it was: a pack over the limit, a finished cell.
    with pytest.raises(carry.CarryError, match=r"packs to .* MB \(allowed: at most"):
        carry.pack(d, max_bytes=3000)  # 4.2 kB of files, 4.6 kB packed
    assert path.read_bytes() == first
    e = _fake_sweep(finished, tmp_path, finished=True)
    with pytest.raises(carry.CarryError, match="has finished"):
        carry.pack(e)
    assert not carry.carry_path(e).exists()
    # A finished cell drops its carry file (untracked here: nothing to commit).
    assert carry.drop(d, tmp_path) == [] and not path.exists()


def test_a_carry_file_reaching_outside_its_sweep_is_refused_and_nothing_is_written(tmp_path):
    import io
    import tarfile

    carry = load_experiment("carry")
    (cell,) = reproduce.select("protocol", ["hopper/a2c/action-thesis"])
    d = reproduce.cell_dir(cell, tmp_path)
    d.mkdir(parents=True)
    with tarfile.open(carry.carry_path(d), "w:gz") as tar:
        for name in ("sweep/config.yaml", "sweep/../../escaped.txt"):
            info = tarfile.TarInfo(name)
            info.size = 3
            tar.addfile(info, io.BytesIO(b"abc"))
    with pytest.raises(carry.CarryError, match=r"member 'sweep/\.\./\.\./escaped.txt' \(allowed"):
        carry.unpack(d)
    assert sorted(p.name for p in d.iterdir()) == [carry.CARRY]
    assert not (tmp_path / "protocol" / "hopper" / "escaped.txt").exists()


def test_pack_refuses_a_running_cell_and_packs_none(tmp_path, capsys):
    stopped, running = reproduce.select("protocol", ["hopper/a2c/action-thesis", "hopper/a2c/psne-thesis"])
    a = _stopped_cell_with_a_checkpoint(stopped, tmp_path)
    b = _stopped_cell_with_a_checkpoint(running, tmp_path)
    (b / "running.pid").write_text(f"{os.getpid()}\n")
    args = ["protocol", "--cells", "hopper/a2c/*", "--results", str(tmp_path), "--pack"]
    assert reproduce.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'hopper/a2c/psne-thesis' is running" in err[0]
    assert not (a / "carry.tar.gz").exists() and not (b / "carry.tar.gz").exists()
    (b / "running.pid").unlink()
    assert reproduce.main(args) == 0
    assert (a / "carry.tar.gz").exists() and (b / "carry.tar.gz").exists()
    # A cell too large to carry (as an SAC checkpoint with its replay buffer) is named and
    # passed over, before its archive is built; the others are packed.
    carry = sys.modules["carry"]
    (b / "carry.tar.gz").unlink()
    big = b / "sweep" / "checkpoint.msgpack"
    with open(big, "r+b") as f:
        f.truncate(2 * carry.MAX_BYTES + 1)
    (a / "carry.tar.gz").unlink()
    assert reproduce.main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "psne-thesis' holds 32 MB to pack (allowed: at most 16 MB" in err[0], err
    assert (a / "carry.tar.gz").exists() and not (b / "carry.tar.gz").exists()


def test_a_carried_cell_is_unpacked_before_its_sweep_resumes_and_its_carry_file_goes(tmp_path, monkeypatch):
    carry = load_experiment("carry")
    (cell,) = reproduce.select("protocol", ["hopper/a2c/action-thesis"])
    d = _stopped_cell_with_a_checkpoint(cell, tmp_path)
    carry.pack(d)
    shutil.rmtree(d / "sweep")
    seen = []

    def finishing_sweep(c, results):  # stands for `resume=`: records what it found, then finishes
        sweep = reproduce.cell_dir(c, results) / "sweep"
        seen.append(sorted(p.name for p in sweep.iterdir()))
        code = f"import pathlib; pathlib.Path({str(sweep / 'sweep.json')!r}).write_text('{{}}')"
        return [sys.executable, "-c", code]

    monkeypatch.setattr(sys.modules["cells"], "sweep_command", finishing_sweep)
    monkeypatch.setattr(reproduce.curves, "update_table", lambda *a: None)
    assert reproduce.main(["protocol", "--cells", cell.name, "--results", str(tmp_path)]) == 0
    assert seen and "checkpoint.msgpack" in seen[0] and "seed=0" in seen[0]
    assert reproduce.cell_state(cell, tmp_path) == "done" and not carry.carry_path(d).exists()


def test_results_of_another_specification_are_refused(tmp_path):
    cell = reproduce.select("thesis", ["hopper/ppo/action"])[0]
    d = _fake_sweep(cell, tmp_path, finished=False)
    reproduce.check_cell_dir(cell, tmp_path)  # its own results: accepted
    (d / "cell.json").write_text(json.dumps({"spec": {"seeds": 3}, "fingerprint": "0" * 16}))
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    proc = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "reproduce.py"), "thesis", "--cells", "hopper/ppo/action",
         "--results", str(tmp_path)],
        capture_output=True, text=True, timeout=60, env=child_env(),
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "another specification" in proc.stderr
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_report_counts_a_seed_as_reaching_the_sparse_reward_at_its_first_positive_return():
    from coherent_jax import plot

    report = _report()

    def run(values):
        steps = np.arange(1, len(values) + 1) * 4096
        return plot.Run(Path("."), "dmc-ball_in_cup", "ppo", "action", 0, steps, np.array(values), {})

    # No episode completed (NaN) and zero returns are not a hit; the first positive one is.
    assert report.reached_reward(run([np.nan, 0.0, 0.0, 3.0, 0.0, 7.0])) == 4 * 4096
    assert report.reached_reward(run([np.nan, 0.0, 0.0])) is None
    assert report.reached_reward(run([-1.0, 0.0])) is None


def test_report_pairs_each_claim_with_its_comparison():
    report = _report()
    assert ("beta=0.01", "psne") in report._pairs("sparse", {"beta=0.01": 0, "beta=0": 0, "psne": 0})
    assert ("coherent", "psne") in report._pairs("thesis", {"coherent": 0, "psne": 0})
    # The ablations' claims compare the coherent method with its variants: the thesis's three
    # components (the chain, analytic integration, last layer) and the exact gradient.
    labels = ["beta=0.01", "beta=0", "beta=1", "coherent-mc", "coherent-mc-all", "coherent-stored", "action"]
    ablation = report._pairs("ablations", dict.fromkeys(labels, 0))
    assert {("beta=0.01", "coherent-mc"), ("coherent-mc", "coherent-mc-all"), ("beta=0.01", "beta=1")} <= set(
        ablation
    )
    assert all("action" not in pair for pair in ablation)


def test_report_reads_ablations_and_beyond_beside_the_thesis_cells(tmp_path):
    report = _report()
    for name in ("halfcheetah/ppo/*", "hopper/a2c/coherent", "hopper/ppo/psne"):
        for cell in reproduce.select("thesis", [name]):
            _fake_sweep(cell, tmp_path, finished=True)
    _fake_sweep(reproduce.select("thesis", ["hopper/a2c/action"])[0], tmp_path, finished=False)
    names = lambda cells: sorted(c.name for c in cells)  # noqa: E731
    # Ablations: the thesis's action and coherent cells of the ablation task, finished ones only.
    ablations = reproduce.select("ablations", ["halfcheetah/ppo/*"])
    assert names(report._reference_cells("ablations", ablations, tmp_path)) == [
        "halfcheetah/ppo/action",
        "halfcheetah/ppo/coherent",
    ]
    # beyond: every finished thesis strategy of each task and algorithm gSDE or pink has run.
    beyond = reproduce.select("beyond", ["hopper/a2c/pink", "halfcheetah/ppo/gsde"])
    assert names(report._reference_cells("beyond", beyond, tmp_path)) == [
        "halfcheetah/ppo/action",
        "halfcheetah/ppo/coherent",
        "halfcheetah/ppo/noisynet",
        "halfcheetah/ppo/psne",
        "hopper/a2c/coherent",
    ]
    assert report._reference_cells("sparse", beyond, tmp_path) == []
    # Their verdicts: coherent against the newer strategies, not the thesis suite's again.
    labels = dict.fromkeys(["coherent", "action", "noisynet", "psne", "gsde", "pink"], 0)
    assert report._pairs("beyond", labels) == [("coherent", "gsde"), ("coherent", "pink")]
    labels.update({"lattice": 0, "pink-exp0.5": 0})
    assert report._pairs("beyond", labels) == [
        ("coherent", "gsde"),
        ("coherent", "pink"),
        ("coherent", "lattice"),
        ("coherent", "pink-exp0.5"),
    ]
    assert report.verdict({"p": 0.8, "low": 0.6, "high": 0.9}, "beyond") == "holds"


def test_report_reads_the_protocol_suite_as_three_comparisons(tmp_path):
    """Protocol cells lose their ``-thesis`` tag; the strategies, the beta ablation (with the
    coherent cell as beta 0.01) and the chain length (read beside the thesis suite's exact
    and the ablations' stored cells) are aggregated and claimed each among themselves."""
    report = _report()
    run = types.SimpleNamespace(settings={"coherent.beta": 0.5})
    label = {c.name: report._label(c, run, "protocol") for c in reproduce.protocol_cells()}
    assert label["hopper/ppo/psne-thesis"] == "psne"
    assert label["walker2d/a2c/coherent-thesis"] == "coherent"
    assert label["halfcheetah/a2c/coherent-thesis-beta0.5"] == "beta=0.5"
    assert label["hopper/ppo/coherent-episode"] == "coherent-episode"
    exact = reproduce.select("thesis", ["hopper/ppo/coherent"])[0]
    assert report._label(exact, run, "protocol") == "coherent-exact"
    assert report._label(exact, run, "thesis") == "coherent"
    labels = ["action", "coherent", "psne", "beta=0", "beta=1", "coherent-episode", "coherent-exact"]
    assert report.label_groups("protocol", labels) == [
        ("", ["action", "coherent", "psne"]),
        ("beta ablation", ["beta=0", "beta=1", "coherent"]),
        ("chain length", ["coherent-episode", "coherent-exact"]),
    ]
    assert report.label_groups("thesis", ["psne", "action"]) == [("", ["action", "psne"])]
    pairs = report._pairs("protocol", dict.fromkeys(labels, 0))
    assert pairs == [
        ("coherent", "action"),
        ("coherent", "psne"),
        ("coherent", "beta=1"),
        ("coherent", "beta=0"),
        ("coherent-episode", "coherent-exact"),
    ]
    # The chain-length cells' references: only once one of them is done, finished ones only.
    assert report._reference_cells("protocol", [], tmp_path) == []
    for name in ("hopper/ppo/coherent", "halfcheetah/ppo/coherent"):
        _fake_sweep(reproduce.select("thesis", [name])[0], tmp_path, finished=True)
    episode = reproduce.select("protocol", ["hopper/ppo/coherent-episode"])
    assert [c.name for c in report._reference_cells("protocol", episode, tmp_path)] == ["hopper/ppo/coherent"]


def test_report_aggregates_only_the_tasks_every_strategy_has_finished():
    report = _report()
    scores = {
        "action": {"hopper": np.array([1.0, 3.0]), "halfcheetah": np.array([10.0, 30.0])},
        "coherent": {"halfcheetah": np.array([20.0, 40.0])},
    }
    norm = report.normalised(scores)
    assert set(norm) == {"action", "coherent"}
    # One task in common, min-max over both strategies' runs of it.
    np.testing.assert_allclose(norm["action"], [[0.0], [2 / 3]])
    np.testing.assert_allclose(norm["coherent"], [[1 / 3], [1.0]])
    # The table says which task it aggregates and which it leaves out, and why.
    assert report.aggregate_table("ppo", "final return", scores, norm)[0] == (
        "**ppo, final return**, normalised per task over 1 task(s)"
        " (halfcheetah; hopper left out until every strategy has finished it):"
    )
    assert report.normalised({"a": {"hopper": np.ones(2)}, "b": {"walker2d": np.ones(2)}}) == {}


# ------------------------------------------------------------------ compact results
curves = reproduce.curves


def _fake_finished_cell(cell, results, seeds=2):
    """A finished cell as a sweep writes it: per point config.yaml, metrics.jsonl (returns
    as floats of every kind, rows logging neither, a partial last line), summary.json, and
    beside them the files that stay local (run.log, TensorBoard, a checkpoint)."""
    d = _fake_sweep(cell, results, finished=True)
    (d / "sweep" / "seed=0").rename(d / "sweep" / "p000-seed=0")
    for seed in range(1, seeds):
        (d / "sweep" / f"p{seed:03d}-seed={seed}").mkdir()
    for seed in range(seeds):
        point = d / "sweep" / f"p{seed:03d}-seed={seed}"
        (point / "config.yaml").write_text(f"seed: {seed}\nenv: {cell.setting('env')}\n")
        rows = [
            {"iteration": 1, "env_steps": 4096, "train/episode_return": None},
            {"iteration": 2, "env_steps": 8192, "train/episode_return": 0.1 + 0.2 + seed},
            {"iteration": 3, "env_steps": 12288, "eval/episode_return": -2.5e-300, "train/episode_return": 0},
            {"iteration": 4, "env_steps": 16384, "eval/episode_return": 1234.5678901234567 * (seed + 1)},
            {"iteration": 5, "env_steps": 16384, "eval/episode_return": float("nan")},
        ]
        text = "".join(json.dumps(r) + "\n" for r in rows)
        (point / "metrics.jsonl").write_text(text + '{"iteration": 6, "env_st')  # killed mid-write
        (point / "summary.json").write_text(json.dumps({"seed": seed}))
        (point / "tb").mkdir()
        (point / "tb" / "events.out.tfevents.1").write_bytes(b"\0" * 64)
        (point / "checkpoint.msgpack").write_bytes(b"\0" * 64)
    for name in ("config.yaml", "grid.json", "sweep.csv", "versions.json"):
        (d / "sweep" / name).write_text("{}\n")
    (d / "run.log").write_text("progress bars\n")
    return d


def _runs(cells, results, metric):
    """What the report reads of `cells`: each point's name, seed, curve and settings."""
    return [
        (r.path.name, r.seed, r.steps.tolist(), r.values.tobytes(), r.settings)
        for c in cells
        for r in curves.load_runs(results, c.suite, c.name, metric)
    ]


def test_curves_table_round_trips_what_the_report_reads(tmp_path):
    report = _report()
    assert {report.METRIC, report.REACH_METRIC} == set(curves.METRICS)
    cells = reproduce.select("sparse", ["dmc-ball_in_cup/ppo/action", "dmc-ball_in_cup/ppo/psne"])
    for cell in cells:
        _fake_finished_cell(cell, tmp_path)
    from_logs = {m: _runs(cells, tmp_path, m) for m in curves.METRICS}
    reach = [row for c in cells for row in report.reach_rows(c, tmp_path)]
    table = curves.build(tmp_path, "sparse")
    data = table.read_bytes()
    assert data[4:8] == b"\0\0\0\0"  # gzip without a time stamp
    # Rebuilding, or building in another order, gives the same bytes.
    curves.update_table(tmp_path, "sparse", [cells[1].name])
    assert table.read_bytes() == data
    table.unlink()
    for cell in reversed(cells):
        curves.update_table(tmp_path, "sparse", [cell.name])
    assert table.read_bytes() == data
    rows = curves.read_table(table)
    assert rows == sorted(rows, key=lambda r: r[:3]) and len(rows) == 2 * 2 * 4  # row 1 logged neither
    # Without the logs the report reads the same curves, bit for bit, from the table.
    for path in tmp_path.glob("sparse/**/metrics.jsonl"):
        path.unlink()
    assert {m: _runs(cells, tmp_path, m) for m in curves.METRICS} == from_logs
    assert [row for c in cells for row in report.reach_rows(c, tmp_path)] == reach
    # A finished cell whose logs are gone keeps its rows when the table is rebuilt.
    assert curves.build(tmp_path, "sparse").read_bytes() == data


def test_commit_adds_only_the_compact_files(tmp_path, monkeypatch):
    cell = reproduce.select("thesis", ["hopper/ppo/action"])[0]
    repo = tmp_path / "repo"
    results = repo / "experiments" / "results"
    d = _fake_finished_cell(cell, results)
    listed = curves.committed_files(d, curves.table_path(results, "thesis"))
    expected = [
        "cell.json",
        *(f"sweep/{f}" for f in ("config.yaml", "grid.json", "sweep.csv", "sweep.json", "versions.json")),
        *(f"sweep/p00{i}-seed={i}/{f}" for i in range(2) for f in ("config.yaml", "summary.json")),
    ]
    assert [p.relative_to(d).as_posix() for p in listed] == expected  # the table does not exist yet
    # experiments/results/.gitignore keeps exactly these (and the suite's table) out of the ignored.
    shutil.copy(ROOT / "experiments" / "results" / ".gitignore", results / ".gitignore")
    git = lambda *a: subprocess.run(["git", "-C", str(repo), *a], capture_output=True, text=True)  # noqa: E731
    if git("init", "-q").returncode != 0:
        pytest.skip("git is not available")
    files = [p.relative_to(repo).as_posix() for p in d.rglob("*") if p.is_file()]
    ignored = set(git("check-ignore", "--no-index", *files).stdout.split())
    assert sorted(set(files) - ignored) == sorted(p.relative_to(repo).as_posix() for p in listed)
    # --commit: the suite's table, updated from the cell's logs, and the cell's small files.
    for key, value in {"NAME": "test", "EMAIL": "test@example.com"}.items():
        monkeypatch.setenv(f"GIT_AUTHOR_{key}", value)
        monkeypatch.setenv(f"GIT_COMMITTER_{key}", value)
    monkeypatch.setattr(reproduce, "ROOT", repo)
    reproduce.commit_cell(cell, results)
    committed = git("show", "--name-only", "--format=%s", "HEAD").stdout.split("\n")
    assert committed[0] == "results: thesis hopper/ppo/action"
    prefix = "experiments/results/thesis/"
    assert sorted(filter(None, committed[1:])) == sorted(
        [prefix + "curves.csv.gz", *(f"{prefix}hopper/ppo/action/{f}" for f in expected)]
    )
    assert [r[:3] for r in curves.read_table(results / "thesis" / "curves.csv.gz")][:2] == [
        ("hopper/ppo/action", "p000-seed=0", 8192),
        ("hopper/ppo/action", "p000-seed=0", 12288),
    ]


def test_a_cell_present_only_as_compact_data_is_done(tmp_path):
    """A clone holds a finished cell's committed files only: it is done, needs nothing, and
    its measured rate still serves the estimates of the cells of its task and algorithm."""
    report = _report()
    done, missing = reproduce.select("thesis", ["hopper/a2c/action", "hopper/a2c/psne"])
    d = _fake_finished_cell(done, tmp_path / "ran")
    table = curves.update_table(tmp_path / "ran", "thesis", [done.name])
    clone = tmp_path / "clone"
    for f in curves.committed_files(d, table):
        target = clone / f.relative_to(tmp_path / "ran")
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, target)
    assert not list(clone.rglob("metrics.jsonl")) and not list(clone.rglob("run.log"))
    assert reproduce.cell_state(done, clone) == "done"
    assert reproduce.progress(done, clone) == (1.0, 1000.0)
    assert reproduce.estimated_seconds(done, clone) == 0.0
    assert [c.name for c, _ in reproduce._finished_cells(clone)] == [done.name]
    assert reproduce.estimated_seconds(missing, clone) == pytest.approx(
        missing.env_steps * reproduce.STRATEGY_COST["psne"] / 1000.0
    )
    proc = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "reproduce.py"), "thesis", "--status", "--cells",
         "hopper/a2c/action", "--results", str(clone)],
        capture_output=True, text=True, timeout=60, env=child_env(),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[:3] == ["hopper/a2c/action", "done", "100.0%"]
    assert len(report.cell_runs(done, clone)) == 2


def test_the_scripts_read_this_checkouts_package(tmp_path):
    """`reproduce.py` (and what it imports in-process: the curves table, the commit) reads
    the package of its own checkout, not another one earlier on the path (a worktree's
    results are made by its own code): a decoy ``coherent_jax`` on PYTHONPATH is not read."""
    decoy = tmp_path / "coherent_jax"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise ImportError('the decoy package was imported')\n")
    code = (
        "import runpy, sys; runpy.run_path(sys.argv[1], run_name='loaded'); "
        "import coherent_jax.runs; print(coherent_jax.runs.__file__)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(ROOT / "experiments" / "reproduce.py")],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(tmp_path)),
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert Path(proc.stdout.strip()).resolve().is_relative_to(ROOT / "coherent_jax")

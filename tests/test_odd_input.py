"""Odd input costs no traceback, no stray directory and no run: one line on stderr naming the key
(or the directory) and what is allowed, exit status 2, and nothing created or changed.

One test per kind of input. Every refusal here happens before anything is compiled; the run
and sweep directories are synthetic (a checkpoint that verifies but holds no restorable state).
"""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import child_env, commit_all, load_experiment

from benchmarks.__main__ import main as bench_main
from coherent_jax import evaluate, sweep, train
from coherent_jax.config import ConfigError, help_text, parse_overrides, to_dict
from coherent_jax.run import rundir
from coherent_jax.run.checkpoint import CHECKPOINT, LoopState, encode_checkpoint, resume_point
from coherent_jax.run.rundir import atomic_write
from coherent_jax.run.sweep import parse_sweep

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "env=pointmass",
    "algo=a2c",
    "num_envs=2",
    "ppo.num_minibatches=1",
    "unroll_length=4",
    "eval_episodes=2",
    "episode_length=20",
    "policy_hidden=[8]",
    "value_hidden=[8]",
    "progress=false",
    "total_steps=400",  # 50 iterations of 8 env steps
]
ITERATIONS = 50


def snapshot(path: Path) -> dict[str, str]:
    """Every file and directory under `path`, with a digest of each file's bytes."""
    return {
        str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
        for p in sorted(path.rglob("*"))
    }


def refused(command, args, capsys, *texts, where: Path | None = None) -> str:
    """`command(args)` exits 2 with one line on stderr holding every text; `where` is unchanged."""
    before = snapshot(where) if where is not None else None
    assert command(args) == 2
    out = capsys.readouterr()
    err = [ln for ln in out.err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("error:"), err
    for text in texts:
        assert text in err[0], err[0]
    assert "compiling" not in out.out
    if where is not None:
        assert snapshot(where) == before, "a refusal changed the directory"
    return err[0]


def rows(n: int) -> str:
    return "".join(json.dumps({"iteration": i, "env_steps": 8 * i}) + "\n" for i in range(1, n + 1))


def write_config(path: Path, cfg) -> None:
    from omegaconf import OmegaConf

    atomic_write(path / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())


def fake_run(path: Path, iteration: int, finished: bool = False, extra=()) -> Path:
    """A run directory as train leaves it, its checkpoint at `iteration` (synthetic state)."""
    cfg = parse_overrides([*TINY, *extra])
    path.mkdir()
    write_config(path, cfg)
    (path / "metrics.jsonl").write_text(rows(iteration))
    blob = encode_checkpoint(cfg, iteration, 8 * iteration, LoopState(eval_key=[0, 1]), b"\x81\xa1a\x01" * 64)
    atomic_write(path / CHECKPOINT, blob)
    if finished:
        (path / "summary.json").write_text("{}")
    return path


def fake_sweep(path: Path, finished: bool = True) -> Path:
    """A finished sweep of ent_coef=[0,0.5] x seeds=2, as sweep leaves it (synthetic state)."""
    plan = parse_sweep([*TINY, "ppo.ent_coef=[0,0.5]", "seeds=2"])
    path.mkdir()
    write_config(path, plan.base)
    (path / "grid.json").write_text(json.dumps({"axes": plan.axes, "seeds": plan.seeds}))
    for p in plan.points:
        (path / p.name).mkdir()
        write_config(path / p.name, p.cfg)
        (path / p.name / "metrics.jsonl").write_text(rows(ITERATIONS))
    loop = LoopState(eval_key=[[0, 1]] * len(plan.points))
    blob = encode_checkpoint(plan.base, ITERATIONS, 8 * ITERATIONS, loop, b"\x81\xa1a\x01" * 64)
    atomic_write(path / CHECKPOINT, blob)
    if finished:
        (path / "sweep.json").write_text("{}")
    return path


# ------------------------------------------------------------------ 1. seeds the key derivation cannot take
def test_seed_2_pow_64_is_refused(tmp_path, capsys):
    refused(
        train.main,
        ["seed=18446744073709551616", f"run_dir={tmp_path / 'run'}"],
        capsys,
        "'seed'",
        "4294967295",
    )
    assert list(tmp_path.iterdir()) == []


def test_seed_2_pow_63_is_refused(tmp_path, capsys):
    refused(
        train.main,
        ["seed=9223372036854775808", f"run_dir={tmp_path / 'run'}"],
        capsys,
        "'seed'",
        "4294967295",
    )
    assert list(tmp_path.iterdir()) == []


def test_sweep_seed_list_with_2_pow_64_is_refused(tmp_path, capsys):
    args = [*TINY, "seed=[0,18446744073709551616]", f"run_dir={tmp_path / 'sweep'}"]
    refused(sweep.main, args, capsys, "'seed'", "4294967295")
    assert list(tmp_path.iterdir()) == []


def test_sweep_seed_2_pow_63_minus_1_with_2_seeds_is_refused(tmp_path, capsys):
    out = f"run_dir={tmp_path / 'sweep'}"
    refused(sweep.main, [*TINY, "seed=9223372036854775807", "seeds=2", out], capsys, "'seed'", "4294967295")
    # The largest seed with one more after it: the sum is what overflows.
    refused(sweep.main, [*TINY, "seed=4294967295", "seeds=2", out], capsys, "'seeds'", "4294967295")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ 2. counts beyond int32
def test_num_envs_100000000_is_refused(tmp_path, capsys):
    refused(train.main, ["num_envs=100000000", f"run_dir={tmp_path / 'run'}"], capsys, "'num_envs'", "int32")
    # A budget that only overflows once rounded up to whole iterations names total_steps.
    refused(train.main, ["total_steps=2147483647", f"run_dir={tmp_path / 'run'}"], capsys, "'total_steps'")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ 3. state that cannot fit in memory
def test_num_envs_10000000_is_refused_before_compiling(tmp_path, capsys):
    from coherent_jax.run.memory import machine_memory

    msg = refused(train.main, ["num_envs=10000000", f"run_dir={tmp_path / 'run'}"], capsys, "'num_envs'")
    assert "GB" in msg and f"this machine has {machine_memory() / 1e9:.1f} GB" in msg
    assert list(tmp_path.iterdir()) == []


def test_everyday_configs_are_not_refused_for_memory():
    """The defaults, a 5-seed sweep, SAC with a 1e6 buffer x 5 seeds fit (24 GB, the smallest machine)."""
    from coherent_jax.run.memory import check_memory

    gb24 = 24 * 2**30
    check_memory(parse_overrides([]), memory=gb24)
    check_memory(parse_overrides([]), points=5, memory=gb24)
    check_memory(parse_overrides(["algo=sac", "sac.buffer_size=1000000"]), points=5, memory=gb24)
    check_memory(parse_overrides(["env=humanoid", "num_envs=1024"]), points=5, memory=gb24)
    with pytest.raises(ConfigError, match="'sac.buffer_size'.*5 sweep points"):
        check_memory(parse_overrides(["algo=sac", "sac.buffer_size=200000000"]), points=5, memory=gb24)


# ------------------------------------------------------------------ 4. a stored config that is not one
def test_resume_of_a_yaml_list_config_is_refused(tmp_path, capsys):
    run = fake_run(tmp_path / "run", 3)
    (run / "config.yaml").write_text("- env\n- lr\n")
    refused(train.main, [f"resume={run}"], capsys, "config.yaml", "list", where=tmp_path)


def test_resume_of_an_empty_config_is_refused_with_or_without_checkpoint(tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "config.yaml").write_text("")
    refused(train.main, [f"resume={bare}"], capsys, "config.yaml", "empty", where=tmp_path)
    run = fake_run(tmp_path / "run", 3)
    (run / "config.yaml").write_text("\n")
    refused(train.main, [f"resume={run}"], capsys, "config.yaml", "empty", where=tmp_path)
    refused(sweep.main, [f"resume={run}"], capsys, "config.yaml", "empty", where=tmp_path)


# ------------------------------------------------------------------ 5. a key given twice
@pytest.mark.parametrize(
    "command,args",
    [
        (train.main, ["lr=0.1", "lr=0.2", "run_dir={tmp}/run"]),
        (sweep.main, ["lr=0.1", "lr=0.2", "run_dir={tmp}/run"]),
        (sweep.main, ["ppo.ent_coef=[0,0.1]", "ppo.ent_coef=[0.5]", "run_dir={tmp}/run"]),
        (bench_main, ["throughput", "lr=0.1", "lr=0.2", "out={tmp}/out.json"]),
        (bench_main, ["physics", "envs=[16]", "envs=[64]", "out={tmp}/out.json"]),
    ],
)
def test_lr_given_twice_is_refused(tmp_path, capsys, command, args):
    key = args[-2].split("=")[0]
    refused(command, [a.format(tmp=tmp_path) for a in args], capsys, f"duplicated key {key!r}")
    assert list(tmp_path.iterdir()) == []


def test_evaluate_option_given_twice_is_refused(tmp_path, capsys):
    run = fake_run(tmp_path / "run", 3)
    refused(
        evaluate.main,
        [str(run), "episodes=3", "episodes=4"],
        capsys,
        "duplicated key 'episodes'",
        where=tmp_path,
    )


def test_resume_given_twice_is_refused(tmp_path, capsys):
    run = fake_run(tmp_path / "run", 3)
    refused(train.main, [f"resume={run}", f"resume={run}"], capsys, "duplicated key 'resume'", where=tmp_path)


# ------------------------------------------------------------------ 6. options the command would ignore
@pytest.mark.parametrize("item", ["resume=runs/x", "run_dir=runs/x", "checkpoint_every=5", "total_steps=100"])
@pytest.mark.parametrize("suite", ["throughput", "coherent", "sac"])
def test_bench_resume_and_run_dir_are_refused(capsys, suite, item):
    refused(bench_main, [suite, item], capsys, f"invalid key {item.split('=')[0]!r}", "does not use it")


def test_evaluate_video_path_without_video_is_refused(tmp_path, capsys):
    run = fake_run(tmp_path / "run", 3)
    out = tmp_path / "v.gif"
    refused(
        evaluate.main, [str(run), f"video_path={out}"], capsys, "'video_path'", "video=true", where=tmp_path
    )
    help_out = subprocess.run(
        [sys.executable, "-m", "coherent_jax.evaluate", "--help"],
        capture_output=True,
        text=True,
        env=child_env(),
    ).stdout
    assert "only with video=true" in help_out


def test_reproduce_results_file_is_refused(tmp_path, capsys):
    reproduce = load_experiment("reproduce")
    results = tmp_path / "results.txt"
    results.write_text("not a directory")
    for extra in ([], ["--status"]):
        refused(
            reproduce.main,
            ["thesis", *extra, "--results", str(results)],
            capsys,
            "'--results'",
            "not a directory",
            where=tmp_path,
        )


# ------------------------------------------------------------------ 7. damaged rows of a finished run
@pytest.mark.parametrize("damage", ["truncated", "garbage_line"])
def test_finished_run_with_damaged_metrics_is_refused(tmp_path, capsys, damage):
    run = fake_run(tmp_path / "run", ITERATIONS, finished=True)
    assert train.main([f"resume={run}"]) == 0  # whole: already complete
    assert "already complete" in capsys.readouterr().out
    lines = (run / "metrics.jsonl").read_text().splitlines(keepends=True)
    if damage == "truncated":
        (run / "metrics.jsonl").write_text("".join(lines[:37]) + lines[37][:10])
    else:
        lines[20] = "}{ not a row\n"
        (run / "metrics.jsonl").write_text("".join(lines))
    msg = refused(train.main, [f"resume={run}"], capsys, "metrics.jsonl is damaged", where=tmp_path)
    assert f"iteration {ITERATIONS}" in msg


def test_unfinished_run_with_rows_lost_before_its_checkpoint_is_refused(tmp_path, capsys):
    run = fake_run(tmp_path / "run", 30)
    (run / "metrics.jsonl").write_text(rows(12))
    refused(train.main, [f"resume={run}"], capsys, "metrics.jsonl is damaged", "12 rows", where=tmp_path)


def test_finished_sweep_with_a_damaged_point_is_refused(tmp_path, capsys):
    out = fake_sweep(tmp_path / "sweep")
    assert sweep.main([f"resume={out}"]) == 0
    capsys.readouterr()
    point = sorted(p for p in out.iterdir() if p.is_dir())[2]
    (point / "metrics.jsonl").write_text(rows(ITERATIONS - 1))
    refused(sweep.main, [f"resume={out}"], capsys, point.name, "damaged", where=tmp_path)


# ------------------------------------------------------------------ 8. checkpoint_every=0
def test_checkpoint_every_0_is_documented_and_a_killed_run_starts_over(tmp_path):
    """0 = only at the end and on signals: a run SIGKILLed mid-way (rows, no checkpoint) resumes
    from the start."""
    assert "0 = only at the end and on SIGINT/SIGTERM" in help_text()
    run = fake_run(tmp_path / "run", 3, extra=["checkpoint_every=0"])
    (run / CHECKPOINT).unlink()
    (run / "metrics.jsonl").write_text(rows(40))
    cfg = parse_overrides([*TINY, "checkpoint_every=0"])
    assert resume_point(run, cfg) is None
    # With periodic checkpoints, 40 rows and none is a lost checkpoint: still refused.
    write_config(run, parse_overrides(TINY))
    with pytest.raises(Exception, match="no checkpoint"):
        resume_point(run, parse_overrides(TINY))


# ------------------------------------------------------------------ 9. a directory in use
HOLD = """
import sys
from pathlib import Path
from coherent_jax.run import rundir
lock = rundir.acquire(Path(sys.argv[1]), "run_dir")
print("holding", flush=True)
sys.stdin.read()
lock.release()
"""


def test_directory_locked_by_a_live_process_is_refused_naming_its_pid(tmp_path, capsys):
    run = fake_run(tmp_path / "run", 3)
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(run)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=child_env(),
    )
    try:
        assert holder.stdout.readline().strip() == "holding"
        pid = f"process {holder.pid}"
        refused(train.main, [f"resume={run}"], capsys, "'resume'", pid, where=tmp_path)
        refused(train.main, [*TINY, f"run_dir={run}"], capsys, "'run_dir'", pid, where=tmp_path)
        assert rundir.holder(run) == str(holder.pid)
    finally:
        holder.stdin.close()  # the holder reads to the end of its input, then exits
        holder.wait(timeout=60)
    # The holder is gone and removed its lock file: the directory is as it was.
    assert not (run / rundir.LOCK).exists() and rundir.holder(run) is None


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    run = fake_run(tmp_path / "run", 3)
    (run / rundir.LOCK).write_text(f"{dead.pid}\n")  # what a SIGKILLed holder leaves behind
    assert rundir.holder(run) is None
    rundir.refuse_if_held(run, "resume")
    with rundir.acquire(run, "resume"):
        assert (run / rundir.LOCK).read_text().strip() == str(os.getpid())
        said = capsys.readouterr().out.strip().splitlines()
        assert said == [f"[coherent_jax] {run / rundir.LOCK}: a stale lock of process {dead.pid}, "
                        "which ended without releasing it, taken over"]  # fmt: skip
        with pytest.raises(ConfigError, match=f"in use by process {os.getpid()}"):
            rundir.acquire(run, "resume")  # a second holder, even in this process, is refused
    assert not (run / rundir.LOCK).exists()
    with rundir.acquire(run, "resume"):  # a lock released as it should be leaves nothing to report
        assert "stale" not in capsys.readouterr().out


# ------------------------------------------------------------------ 10. messages that said the wrong thing
def test_sweep_resume_with_the_same_grid_is_accepted_and_a_changed_one_refused(tmp_path, capsys):
    out = fake_sweep(tmp_path / "sweep")
    for same in (
        [],
        ["ppo.ent_coef=[0,0.5]"],
        ["seeds=2"],
        ["ppo.ent_coef=[0,0.5]", "seeds=2"],
        ["seed=[0,1]"],
    ):
        assert sweep.main([f"resume={out}", *same]) == 0, same
        assert "already complete" in capsys.readouterr().out
    for changed in (
        ["ppo.ent_coef=[0,0.4]"],
        ["seeds=3"],
        ["ppo.ent_coef=0.5"],
        ["lr=[0.1,0.2]"],
        ["seed=[0,2]"],
    ):
        msg = refused(
            sweep.main,
            [f"resume={out}", *changed],
            capsys,
            "a sweep's grid cannot change on resume: ",
            where=tmp_path,
        )
        assert changed[0] in msg and "ppo.ent_coef=[0,0.5] seed=[0,1]" in msg


def test_train_resume_of_a_sweep_dir_is_refused_naming_the_sweep_command(tmp_path, capsys):
    out = fake_sweep(tmp_path / "sweep", finished=False)
    refused(
        train.main,
        [f"resume={out}"],
        capsys,
        f"{out} is a sweep; resume it with python -m coherent_jax.sweep resume={out}",
        where=tmp_path,
    )
    point = sorted(p for p in out.iterdir() if p.is_dir())[0]
    refused(
        train.main,
        [f"resume={point}"],
        capsys,
        "is a point of the sweep",
        f"python -m coherent_jax.sweep resume={out}",
        where=tmp_path,
    )


def test_evaluate_of_a_sweep_root_lists_its_points(tmp_path, capsys):
    out = fake_sweep(tmp_path / "sweep")
    points = sorted(p for p in out.iterdir() if p.is_dir())
    msg = refused(
        evaluate.main, [str(out)], capsys, "this is a sweep; evaluate one of its points: ", where=tmp_path
    )
    assert all(str(p) in msg for p in points)


def test_episode_length_minus_1_message_names_0(tmp_path, capsys):
    refused(
        train.main,
        ["episode_length=-1", f"run_dir={tmp_path / 'run'}"],
        capsys,
        "'episode_length'",
        "an integer >= 1, or 0 for the task's own",
    )
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ 11. provenance
def test_versions_json_records_commit_dirty_flag_and_cpu(tmp_path):
    from coherent_jax.run import rundir
    from coherent_jax.run.rundir import record_versions

    record_versions(tmp_path, None)
    versions = json.loads((tmp_path / "versions.json").read_text())
    assert versions["jax"] and {
        "git_commit",
        "git_dirty",
        "cpu_model",
        "cpu_vector_isa",
        "cpu_family",
        "xla_flags",
    } <= set(versions)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        assert versions["git_commit"] == head.stdout.strip() and isinstance(versions["git_dirty"], bool)
    # Outside a git checkout (or in a checkout that only encloses the package): null, no error.
    assert rundir.git_state(tmp_path) == {"git_commit": None, "git_dirty": None}
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: Test CPU 3000\nflags\t\t: fpu sse4_2 avx avx2 fma\n")
    info = rundir.cpu_info(cpuinfo)
    assert {k: info[k] for k in ("cpu_model", "cpu_vector_isa", "cpu_family")} == {
        "cpu_model": "Test CPU 3000",
        "cpu_vector_isa": "avx2",
        "cpu_family": None,  # not in this cpuinfo: null (tests/test_verify_cpu.py reads a full one)
    }


def test_results_data_do_not_make_the_checkout_dirty_but_code_does(tmp_path):
    from coherent_jax.run import rundir

    repo = tmp_path / "repo"
    (repo / "coherent_jax").mkdir(parents=True)
    (repo / rundir.RESULTS_DATA / "protocol").mkdir(parents=True)
    (repo / "coherent_jax" / "train.py").write_text("x = 1\n")
    curves = repo / rundir.RESULTS_DATA / "protocol" / "curves.csv.gz"
    curves.write_bytes(b"old")
    commit_all(repo)
    assert rundir.git_state(repo)["git_dirty"] is False
    curves.write_bytes(b"new")  # a finished cell's curves, not yet committed
    assert rundir.git_state(repo)["git_dirty"] is False
    (repo / "coherent_jax" / "train.py").write_text("x = 2\n")
    assert rundir.git_state(repo)["git_dirty"] is True


HOPPER_CELLS = ("hopper/a2c/action", "hopper/a2c/coherent", "hopper/ppo/action")


def test_report_shows_commits_and_cpus_and_not_recorded_for_older_cells(tmp_path):
    report = load_experiment("report")
    reproduce = report.reproduce
    old, new, resumed = (reproduce.select("thesis", [name])[0] for name in HOPPER_CELLS)
    for cell, fields in ((old, {}), (new, {"git_commit": "a" * 40, "git_dirty": False}), (resumed, {})):
        d = tmp_path / cell.suite / cell.name / "sweep"
        d.mkdir(parents=True)
        cpu = {"cpu_model": "Test CPU", "cpu_vector_isa": "avx2"} if fields else {}
        (d / "versions.json").write_text(json.dumps({"jax": "0.9.2", **fields, **cpu}))
    # A cell resumed on another commit and machine lists both.
    (d / "versions-resumed-7.json").write_text(
        json.dumps({"git_commit": "b" * 40, "git_dirty": True, "cpu_model": "Other", "cpu_vector_isa": None})
    )
    line = report.verify.provenance_lines([old, new, resumed], {"thesis": tmp_path / "thesis"})[0]
    assert "`aaaaaaaaaaaa` (1 cell)" in line and "`bbbbbbbbbbbb` with uncommitted changes (1 cell)" in line
    assert "not recorded (2 cells)" in line.split("; on CPUs")[0]
    assert "Test CPU (avx2) (1 cell)" in line and "Other (no AVX/SSE4.2) (1 cell)" in line

"""Provenance that can decide: what a run records of its CPU, and how a study's `verify`
tells a code change from a CPU change (coherent_jax.run.rundir, coherent_jax.study.verify).
No JAX, no training: the verdicts are decided from recorded fields, and the last
"Changes bits:" commit from a real git history made here."""

import subprocess

import pytest

from coherent_jax.run import rundir
from coherent_jax.study import verify

EPYC_ZEN3 = {
    "cpu_model": "AMD EPYC",
    "cpu_vendor": "AuthenticAMD",
    "cpu_family": 25,
    "cpu_model_number": 1,
    "cpu_stepping": 1,
    "xla_cpu_isa": "AVX2",
    "xla_flags": "",
    "jaxlib": "0.9.2",
}
EPYC_ZEN2 = {**EPYC_ZEN3, "cpu_family": 23, "cpu_model_number": 49, "cpu_stepping": 0}
DIFFERS = {"result": "differs from iteration 2", "values_compared": 6}


def test_cpu_info_reads_identity_and_caps_the_isa_by_xla_flags(tmp_path, monkeypatch):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(
        "processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\nmodel\t\t: 106\n"
        "model name\t: Test CPU 3000\nstepping\t: 6\nflags\t\t: fpu sse4_2 avx avx2 avx512f fma\n"
        "processor\t: 1\nvendor_id\t: Other\nmodel\t\t: 7\n"
    )
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert rundir.cpu_info(cpuinfo) == {
        "cpu_model": "Test CPU 3000",
        "cpu_vendor": "GenuineIntel",
        "cpu_family": 6,
        "cpu_model_number": 106,
        "cpu_stepping": 6,
        "cpu_vector_isa": "avx512f",
        "xla_cpu_isa": "AVX512",
        "xla_flags": "",
    }
    monkeypatch.setenv("XLA_FLAGS", "  --xla_cpu_max_isa=avx2   --xla_force_host_platform_device_count=2 ")
    info = rundir.cpu_info(cpuinfo)
    assert info["xla_cpu_isa"] == "AVX2" and info["cpu_vector_isa"] == "avx512f"
    assert info["xla_flags"] == "--xla_cpu_max_isa=avx2 --xla_force_host_platform_device_count=2"
    # No /proc/cpuinfo: the identity is null, never an error.
    missing = rundir.cpu_info(tmp_path / "absent")
    assert missing["cpu_family"] is None and missing["cpu_vendor"] is None and missing["xla_cpu_isa"] is None


@pytest.mark.parametrize(
    ("host", "flags", "isa"),
    [
        ("avx2", "", "AVX2"),
        ("avx2", "--xla_cpu_max_isa=AVX512", "AVX2"),  # a cap above the host does not raise it
        ("avx512f", "--xla_cpu_max_isa=AVX512_VNNI", "AVX512"),
        ("avx512f", "--xla_cpu_max_isa=SSE4_2", "SSE4_2"),
        ("avx", "--xla_cpu_max_isa=AVX2 --xla_cpu_max_isa=SSE4_2", "SSE4_2"),  # the last flag wins
        ("avx2", "--xla_cpu_max_isa=NEON", "AVX2 (--xla_cpu_max_isa=NEON)"),
        (None, "--xla_cpu_max_isa=AVX", None),
    ],
)
def test_xla_cpu_isa_is_the_host_isa_capped_by_the_flag(host, flags, isa):
    assert rundir.xla_cpu_isa(host, flags) == isa


def test_a_bit_identical_cell_is_bit_identical_on_any_cpu():
    same = {"result": "bit-identical", "values_compared": 6}
    assert verify.classify(same, EPYC_ZEN2, EPYC_ZEN3, "a" * 40) == same
    nothing = {"result": "nothing to compare", "values_compared": 0}
    assert verify.classify(nothing, {}, EPYC_ZEN3, None) == nothing


def test_a_difference_on_another_cpu_is_not_comparable_naming_both():
    out = verify.classify(DIFFERS, EPYC_ZEN2, EPYC_ZEN3, "a" * 40)
    assert out["result"] == (
        "not comparable: made on CPU AMD EPYC (AuthenticAMD family 23 model 49 stepping 0, XLA for AVX2), "
        "this is CPU AMD EPYC (AuthenticAMD family 25 model 1 stepping 1, XLA for AVX2)"
    )
    assert "changes_bits" not in out
    # The same processor under an XLA flag that changes its code is another CPU for the bits.
    capped = {**EPYC_ZEN3, "xla_cpu_isa": "AVX", "xla_flags": "--xla_cpu_max_isa=AVX"}
    out = verify.classify(DIFFERS, EPYC_ZEN3, capped, "a" * 40)
    assert (
        out["result"].startswith("not comparable:") and "XLA_FLAGS='--xla_cpu_max_isa=AVX'" in out["result"]
    )


def test_a_cell_recording_only_the_cpu_name_is_reported_as_too_little():
    old = {"cpu_model": "AMD EPYC", "cpu_vector_isa": "avx512f"}  # as cells made before the identity
    out = verify.classify(DIFFERS, old, EPYC_ZEN3, "a" * 40)
    assert out["result"] == (
        "differs from iteration 2; the cell records too little of its CPU (only 'AMD EPYC') "
        "to tell a CPU change from a code change"
    )
    assert out["result"].startswith("differs")  # the report's dagger still marks it


def git(repo, *args):
    return subprocess.run(
        ["git", "-C", str(repo), *args], capture_output=True, text=True, check=True
    ).stdout.strip()


def make_history(repo):
    """Four commits: the cell's, one that changes bits, one that mentions them in passing, one more."""
    repo.mkdir()
    git(repo, "init", "-q")
    git(repo, "config", "user.email", "t@example.com")
    git(repo, "config", "user.name", "t")
    hashes = []
    for i, message in enumerate(
        [
            "the cell's commit",
            "whiten by products\n\nChanges bits: every coherent PPO run from its first update",
            "docs: what Changes bits: means (not at a line's start)",
            "tests only; bits unchanged",
        ]
    ):
        (repo / "f.txt").write_text(str(i))
        git(repo, "add", "f.txt")
        git(repo, "commit", "-q", "-m", message)
        hashes.append(git(repo, "rev-parse", "HEAD"))
    return hashes


def test_a_difference_on_the_same_cpu_names_the_last_changes_bits_commit(tmp_path):
    repo = tmp_path / "repo"
    cell, marked, _, head = make_history(repo)
    assert verify.last_changes_bits(cell, repo) == f"{marked[:7]} whiten by products"
    assert verify.last_changes_bits(marked, repo) == f"none since the cell's commit {marked[:12]}"
    assert verify.last_changes_bits(head, repo) == f"none since the cell's commit {head[:12]}"
    assert verify.last_changes_bits("commit unknown", repo) == "the cell's commit is unknown"
    assert verify.last_changes_bits("f" * 40, repo) == f"the cell's commit {'f' * 12} is not in this checkout"

    out = verify.classify(DIFFERS, EPYC_ZEN3, dict(EPYC_ZEN3), cell)
    assert out["result"] == "differs from iteration 2 on the same CPU"
    # Against this checkout's history (the test's cell commit is not in it).
    assert out["changes_bits"] == f"the cell's commit {cell[:12]} is not in this checkout"
    newer = verify.classify(DIFFERS, EPYC_ZEN3, {**EPYC_ZEN3, "jaxlib": "0.9.3"}, "commit unknown")
    assert newer["result"] == "differs from iteration 2 on the same CPU, with jaxlib 0.9.3 (the cell: 0.9.2)"
    assert newer["changes_bits"] == "the cell's commit is unknown"
    entry = {**out, "cell": {"commit": cell, "cpu": "AMD EPYC"}}
    line = verify.line("study/task/ppo/coherent", entry)
    assert line.startswith("study/task/ppo/coherent: differs from iteration 2 on the same CPU (commit ")
    assert line.endswith("6 values compared; last 'Changes bits:' commit: " + out["changes_bits"] + ")")


def test_recorded_keeps_the_cpu_and_version_fields_only():
    versions = {**EPYC_ZEN3, "git_commit": "a" * 40, "python": "3.11.7", "jax": "0.9.2"}
    kept = verify.recorded(versions)
    assert kept == {**EPYC_ZEN3, "jax": "0.9.2"}
    assert set(verify.CPU_KEY) <= set(rundir.cpu_info())  # every run records what verify compares

"""What a study will cost, before it runs (``plan=true``): its cells, the distinct programs
they compile, each program's rate measured by a short probe, and the estimated hours.

Two cells compile the same program when their resolved configs differ only in what a
sweep holds as arrays (the sweepable hyperparameters: beta, lr, ...), the seed and what
does not enter the program (the budget, the output options) and they vmap as many points
(`program_key`). Each distinct program is probed once: its first cell's sweep for
`PROBE_ITERATIONS` iterations in a scratch folder that is deleted afterwards, timed by the
sweep itself (``sweep.json``: compilation, training env steps/s over all points,
evaluation) and by the CPU time the probe's processes used. A cell's estimate is then

    seconds = compile_s + eval_s + env_steps / rate          (rate: env steps/s of all points)
    CPU hours = seconds * cpu_s / wall_s of its probe / 3600

and the study's wall time with W workers on C cores is the cells' seconds summed over
min(W, C / (cpu_s / wall_s)). Probes are kept in a cache (``$XDG_CACHE_HOME/coherent_jax/
study-probes.json``, by CPU model and program), the only file a plan writes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import SWEEPABLE, to_dict
from coherent_jax.config.parse import modern_items
from coherent_jax.run.rundir import cpu_info
from coherent_jax.run.sweep import parse_sweep
from coherent_jax.study.cell import Cell, cell_state, progress, sweep_env
from coherent_jax.study.spec import working_dir

PROBE_ITERATIONS = 3
# Settings that do not enter the compiled program (or that a probe sets itself).
NOT_PROGRAM = (
    "seed", "total_steps", "run_dir", "resume", "progress", "tensorboard", "wandb",
    "wandb_init_timeout", "checkpoint_every", "eval_every",
)  # fmt: skip
PROBE_SETTINGS = ("progress=false", "tensorboard=false", "checkpoint_every=0")


@dataclasses.dataclass(frozen=True)
class Program:
    """A distinct program: its key, a short description, its cells' names, its probe (or None)."""

    key: str
    what: str
    cells: tuple[str, ...]
    probe: dict[str, Any] | None = None


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def program_key(cell: Cell) -> tuple[str, str, int]:
    """(key, description, env steps per iteration) of the program the cell's sweep compiles
    (parsed in the study's folder, as the sweep will be)."""
    plan = parse_sweep([*modern_items(cell.overrides, note=False), f"seeds={cell.seeds}"])
    flat = _flatten(to_dict(plan.base))
    kept = {k: v for k, v in flat.items() if k not in SWEEPABLE and k not in NOT_PROGRAM}
    text = json.dumps({"config": kept, "points": len(plan.points)}, sort_keys=True, default=str)
    key = hashlib.sha256(text.encode()).hexdigest()[:12]
    base = plan.base
    return key, f"{base.env} {base.algo} {base.explore}, {len(plan.points)} points", base.steps_per_iteration


def cache_path() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "coherent_jax" / "study-probes.json"


def _read_cache() -> dict[str, Any]:
    try:
        return json.loads(cache_path().read_text())
    except (OSError, ValueError):
        return {}


def _write_cache(cache: dict[str, Any]) -> None:
    path = cache_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def probe(cell: Cell, cwd: Path, iterations: int, steps_per_iteration: int) -> dict[str, Any]:
    """Runs the cell's sweep for `iterations` iterations in a scratch folder; its timings."""
    total = iterations * steps_per_iteration
    own = ("total_steps", *(k.split("=", 1)[0] for k in PROBE_SETTINGS))
    items = [o for o in modern_items(cell.overrides, note=False) if o.split("=", 1)[0] not in own]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory(prefix="study-probe-") as scratch:
        cmd = [
            sys.executable, "-m", "coherent_jax.sweep", *items, f"total_steps={total}", f"seeds={cell.seeds}",
            *PROBE_SETTINGS, f"run_dir={Path(scratch) / 'sweep'}",
        ]  # fmt: skip
        t0 = time.perf_counter()
        done = subprocess.run(cmd, cwd=cwd, env=sweep_env(), capture_output=True, text=True, check=False)
        wall = time.perf_counter() - t0
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            raise RuntimeError(f"the probe of cell {cell.name!r} exited {done.returncode}: {tail[0]}")
        summary = json.loads((Path(scratch) / "sweep" / "sweep.json").read_text())
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "rate": float(summary["sweep_env_steps_per_s"]),
        "compile_s": float(summary.get("compile_s", 0.0)),
        "eval_s": float(summary.get("eval_s", 0.0)),
        "cores_used": round(cpu / max(wall, 1e-9), 2),
        "iterations": iterations,
        "date": time.strftime("%Y-%m-%d"),
    }


def programs(cells: Sequence[Cell], cwd: Path) -> tuple[list[Program], dict[str, tuple[str, int]]]:
    """The distinct programs of `cells` (in order of first use) and cell name -> (key, steps
    per iteration)."""
    of: dict[str, tuple[str, int]] = {}
    found: dict[str, Program] = {}
    with working_dir(cwd):
        for cell in cells:
            key, what, spi = program_key(cell)
            of[cell.name] = (key, spi)
            p = found.get(key, Program(key, what, ()))
            found[key] = dataclasses.replace(p, cells=(*p.cells, cell.name))
    return list(found.values()), of


def measure(
    cells: Sequence[Cell], cwd: Path, iterations: int, log=print
) -> tuple[list[Program], dict[str, tuple[str, int]]]:
    """Every distinct program with its probe: from the cache, else probed now (and cached)."""
    progs, of = programs(cells, cwd)
    cache = _read_cache()
    here = cpu_info()["cpu_model"] or "unknown CPU"
    known = cache.setdefault(here, {})
    by_name = {c.name: c for c in cells}
    out = []
    for p in progs:
        if p.key not in known:
            log(f"[study] probing program {p.key} ({p.what}): {iterations} iterations of {p.cells[0]}")
            known[p.key] = probe(by_name[p.cells[0]], cwd, iterations, of[p.cells[0]][1])
            _write_cache(cache)
        out.append(dataclasses.replace(p, probe=known[p.key]))
    return out, of


def cell_seconds(cell: Cell, study_dir: Path, measured: dict[str, Any]) -> float:
    """Seconds the cell still needs by its program's probe (0 for a finished cell)."""
    if cell_state(cell, study_dir) == "done":
        return 0.0
    fraction, _ = progress(cell, study_dir)
    return measured["compile_s"] + measured["eval_s"] + (1 - fraction) * cell.env_steps / measured["rate"]


def plan_text(cells: Sequence[Cell], study_dir: Path, progs: list[Program], of, workers: int) -> str:
    """The plan: the programs with their probes, each cell's estimate, the totals."""
    probes = {p.key: p.probe for p in progs}
    lines = [f"{len(cells)} cells, {len(progs)} distinct programs", "", "program       cells  probe"]
    for p in progs:
        m = p.probe
        lines.append(
            f"{p.key}  {len(p.cells):5d}  {p.what}: {m['rate']:,.0f} env steps/s, "
            f"compile {m['compile_s']:.0f} s, {m['cores_used']:.1f} cores"
        )
    lines += ["", f"{'cell':44s} {'program':12s} {'env steps':>10s} {'state':8s} {'hours':>7s}"]
    total = cpu = 0.0
    for cell in cells:
        m = probes[of[cell.name][0]]
        s = cell_seconds(cell, study_dir, m)
        total, cpu = total + s, cpu + s * m["cores_used"]
        lines.append(
            f"{cell.name:44s} {of[cell.name][0]:12s} {cell.env_steps / 1e6:9.2f}M "
            f"{cell_state(cell, study_dir):8s} {s / 3600:7.2f}"
        )
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    used = max((p.probe["cores_used"] for p in progs), default=1.0)
    wall = total / max(1.0, min(workers, cores / max(used, 1e-9)))
    lines += [
        "",
        f"estimated: {cpu / 3600:.2f} CPU hours; {total / 3600:.2f} h of this machine one cell at a time, "
        f"about {wall / 3600:.2f} h with workers={workers} on {cores} cores",
    ]
    return "\n".join(lines)


def cached_rates(cells: Sequence[Cell], cwd: Path) -> dict[str, float]:
    """Cell name -> the env steps/s a cached probe of its program measured on this CPU model
    (what `coherent_jax.study.cost` reads before the cell logs its own); no probe is run."""
    known = _read_cache().get(cpu_info()["cpu_model"] or "unknown CPU", {})
    if not known:
        return {}
    _, of = programs(cells, cwd)
    return {name: known[key]["rate"] for name, (key, _) in of.items() if key in known}

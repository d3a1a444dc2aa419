"""What git keeps of a study: a finished cell's kept files committed (``commit=true``), and a
stopped cell's state packed to its carry file (``pack=true``) so that a clone elsewhere
continues it (`coherent_jax.study.carry`). The git repository is the one holding the study."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from coherent_jax.study import carry, curves
from coherent_jax.study.cell import Cell, cell_dir, cell_state, progress


def _git_commit(root: Path, files: Sequence[str], message: str) -> None:
    subprocess.run(["git", "-C", str(root), "add", "--", *files], check=True)
    subprocess.run(["git", "-C", str(root), "commit", "-q", "-m", message, "--", *files], check=False)


def commit_cell(cell: Cell, study_dir: Path) -> None:
    """Commits a finished cell's compact results: its study's curves table, updated from the
    cell's per-seed logs, and the cell's small files (`curves.committed_files`). The logs
    themselves stay local (experiments/results/.gitignore)."""
    table = curves.update_table(study_dir, [cell.name])
    files = [str(f) for f in curves.committed_files(cell_dir(cell, study_dir), table)]
    files += carry.drop(cell_dir(cell, study_dir), study_dir)
    _git_commit(study_dir, files, f"results: {cell.suite} {cell.name}")


def pack_cells(cells: Sequence[Cell], study_dir: Path, commit: bool) -> int:
    """``pack=true``: each stopped cell's carry file; none if a selected cell is running (exit 2).
    A cell that cannot be carried (too large: SAC) is named and passed over (exit 1)."""
    running = [c.name for c in cells if cell_state(c, study_dir) == "running"]
    if running:
        print(
            f"error: cell {running[0]!r} is running (allowed: stopped cells; SIGTERM checkpoints it)",
            file=sys.stderr,
        )
        return 2
    packed, failed = [], 0
    for cell in (c for c in cells if cell_state(c, study_dir) == "stopped"):
        try:
            packed.append(str(carry.pack(cell_dir(cell, study_dir))))
        except carry.CarryError as exc:
            print(f"error: {exc}", file=sys.stderr)
            failed += 1
            continue
        size = Path(packed[-1]).stat().st_size / 1e6
        print(f"[study] {cell.name}: {100 * progress(cell, study_dir)[0]:.1f}% done, packed in {size:.2f} MB")
    if commit and packed:
        _git_commit(study_dir, packed, f"results: carry {len(packed)} stopped cells of {cells[0].suite}")
    return 1 if failed else 0

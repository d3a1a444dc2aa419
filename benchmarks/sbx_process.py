"""The ``sbx`` suite's other process: SBX's venv (made on first use) and its driver.

SBX (``sbx-rl``) needs Stable-Baselines3 and so PyTorch, neither of which the package
installs: it runs in a venv of its own, ``.venv-sbx/`` in the repository's root by default
(git-ignored), created from ``benchmarks/sbx-requirements.txt`` with ``python -m venv``
and pip the first time the suite runs. `Driver` runs ``benchmarks/sbx_driver.py`` with
that venv's Python and speaks its protocol: one JSON line in, one ``@sbx {...}`` line out.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parents[1]
REQUIREMENTS = ROOT / "benchmarks" / "sbx-requirements.txt"
DRIVER = ROOT / "benchmarks" / "sbx_driver.py"
DEFAULT_VENV = ".venv-sbx"  # in the repository's root (.gitignore)
MARK = "@sbx "  # the driver's result lines (sbx_driver.MARK)
# Written into the venv once pip has installed the requirements: their hash, so that a
# changed requirements file installs again.
STAMP = "sbx-requirements.sha256"


def venv_path(text: str) -> Path:
    """The venv's folder: ``text`` as given if absolute, else under the repository's root."""
    path = Path(text).expanduser()
    return path if path.is_absolute() else ROOT / path


def venv_python(venv: Path) -> Path:
    """The venv's Python (POSIX layout, or Windows')."""
    posix = venv / "bin" / "python"
    return posix if posix.exists() or not (venv / "Scripts").exists() else venv / "Scripts" / "python.exe"


def requirements_hash(path: Path = REQUIREMENTS) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def venv_ready(venv: Path) -> bool:
    """Whether ``venv`` has its Python and the current requirements installed (its stamp)."""
    stamp = venv / STAMP
    return venv_python(venv).exists() and stamp.exists() and stamp.read_text().strip() == requirements_hash()


def ensure_venv(venv: Path, log: Callable[[str], None]) -> Path:
    """The venv's Python, after creating the venv and installing the requirements if needed.

    A venv without the stamp of the current requirements (new, or made from an older
    file) gets ``pip install -r benchmarks/sbx-requirements.txt``; pip's own output goes
    to the terminal. Raises `RuntimeError` if a step fails.
    """
    python = venv_python(venv)
    if venv_ready(venv):
        return python
    if not python.exists():
        log(f"[bench] creating SBX's venv {venv} (python -m venv) ...")
        _check_call([sys.executable, "-m", "venv", str(venv)], "python -m venv")
    log(f"[bench] installing {REQUIREMENTS.relative_to(ROOT)} into {venv} (pip; once) ...")
    _check_call(
        [str(python), "-m", "pip", "install", "--disable-pip-version-check", "-r", str(REQUIREMENTS)],
        "pip install",
    )
    (venv / STAMP).write_text(requirements_hash() + "\n")
    return python


def _check_call(command: list[str], what: str) -> None:
    status = subprocess.call(command)
    if status != 0:
        raise RuntimeError(f"{what} failed (exit status {status}): {' '.join(command)}")


def read_record(stream: Iterable[str]) -> dict[str, Any] | None:
    """The next ``@sbx`` line's JSON object from ``stream`` (other lines skipped); None at its end."""
    for line in stream:
        if line.startswith(MARK):
            return json.loads(line[len(MARK) :])
    return None


class Driver:
    """SBX's SAC in its own process (``python -I benchmarks/sbx_driver.py``), built and warmed up.

    ``Driver(python, settings)`` starts it, sends ``settings`` and waits for its ``ready``
    record (`ready`); ``run(k)`` times k more iterations there; ``close()`` ends it (also
    as a context manager). The driver's stderr goes to a temporary file, whose end a
    failure quotes.
    """

    def __init__(self, python: Path, settings: dict[str, Any]):
        self._stderr: IO[str] = tempfile.TemporaryFile("w+")
        # -I: the driver's folder stays off sys.path (benchmarks/sbx.py would hide SBX's
        # package), and PYTHONPATH and the user's site are ignored: the venv alone.
        self._proc = subprocess.Popen(
            [str(python), "-I", str(DRIVER)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
            cwd=ROOT,
        )
        try:
            self.ready = self._send(settings)
            if not self.ready.get("ready"):
                raise RuntimeError(f"SBX's driver did not start: {self.ready}")
        except BaseException:
            self.close()
            raise

    def _send(self, message: dict[str, Any]) -> dict[str, Any]:
        assert self._proc.stdin is not None and self._proc.stdout is not None
        try:
            self._proc.stdin.write(json.dumps(message) + "\n")
            self._proc.stdin.flush()
        except BrokenPipeError:
            pass  # the driver has ended: its stderr says why, below
        record = read_record(self._proc.stdout)
        if record is None:
            self._stderr.seek(0)
            tail = self._stderr.read()[-3000:]
            raise RuntimeError(f"SBX's driver ended (exit status {self._proc.wait()}):\n{tail}")
        return record

    def run(self, iterations: int) -> dict[str, Any]:
        """``iterations`` more iterations of SBX's SAC: their times, updates and env steps."""
        return self._send({"iterations": iterations})

    def close(self) -> None:
        if self._proc.poll() is None:
            try:
                assert self._proc.stdin is not None
                self._proc.stdin.write(json.dumps({"quit": True}) + "\n")
                self._proc.stdin.close()
                self._proc.wait(timeout=60)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        self._stderr.close()

    def __enter__(self) -> Driver:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

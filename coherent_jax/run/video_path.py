"""Where an evaluation video goes and in which format (`coherent_jax.run.video` renders and
writes it): MP4 with ``ffmpeg`` on the PATH, else GIF."""

from __future__ import annotations

import shutil
from pathlib import Path

from coherent_jax.config import cli

FORMATS = (".mp4", ".gif")


def default_suffix() -> str:
    """``.mp4`` where ``ffmpeg`` is on the PATH, else ``.gif`` (Pillow writes those)."""
    return ".mp4" if shutil.which("ffmpeg") else ".gif"


PATH_ALLOWED = "a writable .gif path, or .mp4 when ffmpeg is on the PATH"


def check_path(text: str) -> str:
    """A ``video_path`` that can be written: ``.gif``, or ``.mp4`` with ``ffmpeg``; raises `ValueError`."""
    suffix = Path(text).suffix.lower()
    if suffix not in FORMATS or (suffix == ".mp4" and not shutil.which("ffmpeg")):
        raise ValueError(text)
    return cli.output_file(text)

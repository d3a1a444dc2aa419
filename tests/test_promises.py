"""Promises that hold: every speed figure the README states is one docs/benchmarks.md
measured, on a date (the README's "Speed:" paragraph, each env steps/s rate and each ratio
such as ``0.49-0.60x``, found as a number of its own in a section of docs/benchmarks.md that
gives its date); the committed results stay under 20 MB."""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
NUMBER = r"\d[\d,]*(?:\.\d+)?"


def speed_paragraph(readme: str) -> str:
    start = readme.index("\nSpeed:")
    end = readme.find("\n\n", start + 1)
    return readme[start:end]


def figures(paragraph: str) -> list[str]:
    """The rates (``N env steps/s``) and the ratios (``a-bx`` or ``ax``) of a paragraph."""
    text = " ".join(paragraph.split())
    rates = re.findall(rf"({NUMBER}) env steps/s", text)
    ratios = []
    for low, high in re.findall(rf"({NUMBER})(?:-({NUMBER}))?x\b", text):
        ratios += [low] + ([high] if high else [])
    return rates + ratios


def sections(doc: str) -> list[str]:
    return re.split(r"\n(?=#{2,4} )", doc)


def test_every_readme_speed_figure_is_measured_in_benchmarks_md_with_a_date():
    paragraph = speed_paragraph((ROOT / "README.md").read_text())
    found = figures(paragraph)
    assert len(found) >= 3, paragraph  # a rate and a range of ratios at least
    doc = sections((ROOT / "docs" / "benchmarks.md").read_text())
    for figure in found:
        own = re.compile(rf"(?<![\d.,]){re.escape(figure)}(?![\d,]|\.\d)")
        homes = [s for s in doc if own.search(s)]
        assert homes, f"{figure} (README's speed line) is nowhere in docs/benchmarks.md"
        assert any(DATE.search(s) for s in homes), f"{figure}: docs/benchmarks.md gives it without a date"


def test_the_figure_finder_reads_rates_and_ranges():
    text = "at 8,009 env steps/s (Intel) and 16,100 env steps/s, at 0.49-0.60x and 1.5x of"
    assert figures(text) == ["8,009", "16,100", "0.49", "0.60", "1.5"]


RESULTS_LIMIT = 20 * 10**6  # bytes of the files git tracks under experiments/results/


def test_the_committed_results_stay_under_20_mb():
    """Counted as git stores them (the files' bytes); ``du`` reports about 3x more on a
    4 KiB-block filesystem, since most of the 2,700 files are a few hundred bytes."""
    listed = subprocess.run(
        ["git", "-C", str(ROOT), "ls-files", "-z", "experiments/results"], capture_output=True, check=False
    )
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    files = [ROOT / f for f in listed.stdout.decode().split("\0") if f]
    total = sum(f.stat().st_size for f in files if f.is_file())
    assert len(files) > 100 and total < RESULTS_LIMIT, (len(files), total)

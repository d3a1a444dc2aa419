"""``python -m benchmarks [SUITE] [key=value ...]``: parse, refuse bad input in one line, run."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from benchmarks import COST_MACHINE, DEFAULT_SUITE, IGNORED, SUITES
from coherent_jax.config import ConfigError, cli
from coherent_jax.exit_codes import EXIT_BAD_INPUT


def suite_module(name: str) -> ModuleType:
    """The module of suite ``name`` (`benchmarks.<name>`)."""
    return importlib.import_module(f"benchmarks.{name}")


def help_text() -> str:
    """Every suite's cost at its defaults (`COST`, measured) and its own settings with their defaults."""
    lines = [
        "usage: python -m benchmarks [SUITE] [key=value ...]",
        f"suites: {', '.join(SUITES)} (default: {DEFAULT_SUITE})",
        f"COST: each suite's wall time at its defaults, measured {COST_MACHINE}",
    ]
    for name in SUITES:
        module = suite_module(name)
        lines += [
            "",
            f"{name} suite COST: {module.COST}",
            f"{name} suite options (key=default):",
            *cli.help_lines(module.KEYS),
        ]
        fixed = getattr(module, "FIXED", None)
        if fixed is not None:
            ignored = getattr(module, "IGNORED_KEYS", IGNORED)
            lines.append(
                "  and every training option of `python -m coherent_jax.train --help` except "
                + ", ".join(fixed)
                + " (set by the suite)"
                + (" and " + ", ".join(ignored) + " (the suite does not use them)" if ignored else "")
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Runs one suite; returns the exit status (2 for bad input, before anything runs)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(help_text())
        return 0
    if not argv or "=" in argv[0]:  # no suite named: the default one
        argv = [DEFAULT_SUITE, *argv]
    name, items = argv[0], argv[1:]
    if name not in SUITES:
        print(f"error: unknown suite {name!r}; valid suites: {', '.join(SUITES)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    suite = suite_module(name)
    try:
        suite.parse(items)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    result = suite.run(items)
    print()
    print(suite.format_table(result), flush=True)
    # A suite that checks a bound (gradient) says whether it held.
    return suite.exit_status(result) if hasattr(suite, "exit_status") else 0


if __name__ == "__main__":
    sys.exit(main())

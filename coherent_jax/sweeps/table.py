"""A sweep's aggregate over seeds: rows per non-seed point, as CSV and as the printed table."""

from __future__ import annotations

import csv
import io
import statistics
from typing import Any


def fmt(value: Any) -> str:
    """A grid value as names and tables show it (floats in ``%g``)."""
    return f"{value:g}" if isinstance(value, float) else str(value)


def aggregate(plan: Any, summaries: list[dict]) -> list[dict]:
    """Mean and sample standard deviation (ddof 1; None with fewer than two finite
    returns) over seeds of the final eval return, per non-seed point."""
    groups: dict[tuple, list[dict]] = {}
    for s in summaries:
        groups.setdefault(tuple(s[k] for k in plan.axes), []).append(s)
    rows = []
    for values, members in groups.items():
        returns = [m["final_eval_return"] for m in members if m["final_eval_return"] is not None]
        rows.append(
            {
                **dict(zip(plan.axes, values, strict=True)),
                "seeds": len(members),
                "final_eval_return_mean": statistics.fmean(returns) if returns else None,
                "final_eval_return_std": statistics.stdev(returns) if len(returns) > 1 else None,
                "non_finite": len(members) - len(returns),
            }
        )
    return rows


def to_csv(plan: Any, rows: list[dict]) -> str:
    """`aggregate`'s rows as ``sweep.csv``: the axes, the seed count, mean and std, non-finite seeds."""
    buf = io.StringIO()
    columns = [*plan.axes, "seeds", "final_eval_return_mean", "final_eval_return_std", "non_finite"]
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def format_table(plan: Any, rows: list[dict]) -> str:
    """`aggregate`'s rows as the table a finished sweep prints: mean ± sample sd over the
    n seeds with a finite return (`summary_text`)."""
    header = (
        "".join(f"{k:>12}" for k in plan.axes)
        + f"{'seeds':>7}  final eval return, mean ± sd (sample sd over the n finite seeds)"
    )
    lines = [header]
    for r in rows:
        value = summary_text(
            r["final_eval_return_mean"], r["final_eval_return_std"], r["seeds"] - r["non_finite"]
        )
        lines.append("".join(f"{fmt(r[k]):>12}" for k in plan.axes) + f"{r['seeds']:>7}  {value}")
    return "\n".join(lines)


def summary_text(mean: float | None, sd: float | None, n: int) -> str:
    """``92.6 ± 26.6 (n=2)``: a mean, its sample sd and the count; one value has no sd."""
    if mean is None:
        return "non-finite"
    if sd is None:
        return f"{mean:10.1f} (n={n})"
    return f"{mean:10.1f} ± {sd:.1f} (n={n})"

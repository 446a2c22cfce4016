"""The files of a batch (:mod:`iceg.batch`): one table of all runs, timings apart.

- ``summary.csv``: one row per run in spec order (log, variant, seed), its status, error and
  metrics; no wall times, so the same spec gives the same file with any number of workers;
- ``timings.csv``: wall time of each run (seconds, ms per scan);
- ``summary.md``: the runs' table (metrics, time, failures), a per-variant table (means
  over the successful runs, failure count) and a per-log table of each variant over its
  seeds (mean, median and worst error and fraction of keyframes matched; false loop
  closures summed);
- ``variants.png``: the variants compared per log (trajectory or relation error, ms per scan).
"""

from __future__ import annotations

import csv
import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from iceg_common.atomic import atomic_write

#: Metric columns in table order (others follow, sorted).
METRIC_ORDER = (
    "scans",
    "nodes",
    "sm_per_kf",
    "match_failures",
    "lc_accepted",
    "lc_false",
    "lc_disputed",
    "rel_trans_m",
    "rel_rot_deg",
    "rel_matched",
    "ate_m",
    "end_m",
    "online_max_m",
    "odom_ate_m",
    "sm_nees",
    "odo_nees",
)
#: Identity columns of ``summary.csv``.
ID_COLUMNS = ("run_id", "log", "variant", "seed", "status", "error")
#: Metrics compared in the plot, the first one the runs have.
PLOT_METRICS = ("ate_m", "rel_trans_m")
#: Errors summarised over the seeds of each log and variant (mean, median, worst: largest).
SPREAD_METRICS = ("rel_trans_m", "rel_rot_deg", "ate_m")
#: Fractions summarised so too, the worst the smallest: the keyframes with a scan-match
#: factor, the one figure of a log without a reference.
SPREAD_FRACTIONS = ("sm_per_kf",)
#: Significant digits of the floats in the tables.
DIGITS = 6


@dataclass(frozen=True)
class BatchReport:
    """What a batch wrote.

    Attributes:
        rows: One dict per run, spec order (``run_id``, ``log``, ``variant``, ``seed``,
            ``status``, ``error``, ``metrics``, ``seconds``).
        summary_csv, timings_csv, markdown, plot: The files written (``plot`` None when no
            run has a comparable metric).
    """

    rows: list[dict[str, Any]]
    summary_csv: Path
    timings_csv: Path
    markdown: Path
    plot: Path | None

    @property
    def n_failed(self) -> int:
        """Runs that failed or timed out."""
        return sum(r["status"] != "ok" for r in self.rows)


def metric_columns(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Metric names present in any row: :data:`METRIC_ORDER` first, then the others."""
    present = {k for r in rows for k in r.get("metrics", {})}
    return [m for m in METRIC_ORDER if m in present] + sorted(present - set(METRIC_ORDER))


def fmt(value: Any) -> str:
    """A table cell: floats with :data:`DIGITS` significant digits, NaN/None empty."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return "" if not math.isfinite(value) else f"{value:.{DIGITS}g}"
    return str(value)


def _ms_per_scan(row: dict[str, Any]) -> float:
    scans = row.get("metrics", {}).get("scans")
    sec = row.get("seconds")
    if not scans or sec is None or not math.isfinite(sec):
        return math.nan
    return 1e3 * float(sec) / int(scans)


def write_report(name: str, rows: list[dict[str, Any]], out: Path) -> BatchReport:
    """Write the batch files into ``out``; return what was written."""
    metrics = metric_columns(rows)
    summary, timings = out / "summary.csv", out / "timings.csv"
    _write_csv(
        summary,
        [*ID_COLUMNS, *metrics],
        [
            [fmt(r.get(c)) for c in ID_COLUMNS] + [fmt(r["metrics"].get(m)) for m in metrics]
            for r in rows
        ],
    )
    _write_csv(
        timings,
        ["run_id", "seconds", "ms_per_scan"],
        [[r["run_id"], fmt(float(r["seconds"])), fmt(_ms_per_scan(r))] for r in rows],
    )
    md = out / "summary.md"
    with atomic_write(md) as fh:
        fh.write(markdown(name, rows, metrics))
    plot = write_plot(name, rows, out / "variants.png")
    return BatchReport(rows, summary, timings, md, plot)


def _write_csv(path: Path, header: Sequence[str], body: list[list[str]]) -> None:
    with atomic_write(path) as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(body)


def _md_table(header: Sequence[str], body: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in body]
    return "\n".join(lines) + "\n"


def markdown(name: str, rows: Sequence[dict[str, Any]], metrics: Sequence[str]) -> str:
    """The markdown summary: every run, then the variants' means (successful runs)."""
    n_bad = sum(r["status"] != "ok" for r in rows)
    head = f"# Batch {name}\n\n{len(rows)} runs, {n_bad} failed or timed out.\n\n## Runs\n\n"
    body = [
        [r["log"], r["variant"], fmt(r.get("seed")), r["status"]]
        + [fmt(r["metrics"].get(m)) for m in metrics]
        + [fmt(float(r["seconds"])), fmt(_ms_per_scan(r)), r.get("error", "")]
        for r in rows
    ]
    runs = _md_table(
        ["log", "variant", "seed", "status", *metrics, "time s", "ms/scan", "error"], body
    )
    return (
        head
        + runs
        + "\n## Variants (means over successful runs)\n\n"
        + _variant_table(rows, metrics)
        + "\n## Logs over seeds (successful runs: mean / median / worst)\n\n"
        + seed_table(rows)
    )


def _mean(values: list[float]) -> float:
    ok = [v for v in values if v is not None and math.isfinite(v)]
    return sum(ok) / len(ok) if ok else math.nan


def _variant_table(rows: Sequence[dict[str, Any]], metrics: Sequence[str]) -> str:
    names = list(dict.fromkeys(r["variant"] for r in rows))
    body = []
    for v in names:
        mine = [r for r in rows if r["variant"] == v]
        ok = [r for r in mine if r["status"] == "ok"]
        body.append(
            [v, str(len(mine)), str(len(mine) - len(ok))]
            + [fmt(_mean([float(r["metrics"].get(m, math.nan)) for r in ok])) for m in metrics]
            + [fmt(_mean([_ms_per_scan(r) for r in ok]))]
        )
    return _md_table(["variant", "runs", "failed", *metrics, "ms/scan"], body)


def seed_table(rows: Sequence[dict[str, Any]]) -> str:
    """A markdown table, one row per log and variant (rows as in :class:`BatchReport`; the
    seed is not read): its runs over the seeds, the failed ones, each of
    :data:`SPREAD_METRICS` and :data:`SPREAD_FRACTIONS` the log has as
    ``mean / median / worst`` over the successful runs (one seed's luck is not a change's
    effect: a loop closure found or missed moves a log's error by more than most changes do),
    and the false loop closures summed."""
    present = [
        m
        for m in (*SPREAD_METRICS, *SPREAD_FRACTIONS)
        if any(m in r.get("metrics", {}) for r in rows)
    ]
    has_false = any("lc_false" in r.get("metrics", {}) for r in rows)
    body = []
    for log in dict.fromkeys(r["log"] for r in rows):
        for v in dict.fromkeys(r["variant"] for r in rows if r["log"] == log):
            mine = [r for r in rows if r["log"] == log and r["variant"] == v]
            ok = [r for r in mine if r["status"] == "ok"]
            cells = [log, v, str(len(mine)), str(len(mine) - len(ok))]
            for m in present:
                worst = min if m in SPREAD_FRACTIONS else max
                cells.append(_spread([r["metrics"].get(m) for r in ok], worst))
            if has_false:
                false = [r["metrics"]["lc_false"] for r in ok if "lc_false" in r["metrics"]]
                cells.append(str(sum(false)) if false else "")
            body.append(cells)
    header = ["log", "variant", "runs", "failed", *present] + (["lc_false"] if has_false else [])
    return _md_table(header, body)


def _spread(values: Sequence[Any], worst: Callable[[list[float]], float] = max) -> str:
    """``mean / median / worst`` of the finite values, "" without one."""
    ok = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not ok:
        return ""
    return " / ".join(fmt(x) for x in (statistics.fmean(ok), statistics.median(ok), worst(ok)))


def write_plot(name: str, rows: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """Grouped bars, one group per log and one bar per variant (mean over seeds): the first
    of :data:`PLOT_METRICS` the runs have, and ms per scan; a log whose runs of a variant
    all failed shows an ``x``. None (nothing written) without a comparable metric."""
    metric = next((m for m in PLOT_METRICS if any(m in r.get("metrics", {}) for r in rows)), None)
    if metric is None:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    logs = list(dict.fromkeys(r["log"] for r in rows))
    names = list(dict.fromkeys(r["variant"] for r in rows))
    width = 0.8 / max(1, len(names))
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 1.2 * len(logs) * len(names)), 7))
    for ax, (label, get) in zip(
        axes,
        (
            (metric, lambda r: float(r["metrics"].get(metric, math.nan))),
            ("ms per scan", _ms_per_scan),
        ),
        strict=True,
    ):
        for k, v in enumerate(names):
            for i, log in enumerate(logs):
                mine = [r for r in rows if r["log"] == log and r["variant"] == v]
                val = _mean([get(r) for r in mine if r["status"] == "ok"])
                x = i + (k - (len(names) - 1) / 2) * width
                if math.isfinite(val):
                    ax.bar(x, val, width, color=f"C{k}", label=v if i == 0 else None)
                elif mine:
                    ax.plot(x, 0.0, "x", color=f"C{k}", markersize=10)
        ax.set_xticks(range(len(logs)), logs)
        ax.set_ylabel(label)
    axes[0].legend(fontsize="small")
    axes[0].set_title(f"{name}: variants per log (x: all runs failed)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

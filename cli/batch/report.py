"""``statfit batch report``: a batch you can look at — an HTML page and a CSV, one row per input."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from statfit_cli.common import PROGRESS_LINE_SECONDS


def report(
    out_dir: Path = typer.Argument(..., metavar="DIR", help="A batch's output folder (statfit batch register or "
                                   "render --out-dir).", show_default=False),
    out: Path = typer.Option(None, "--out", help="The HTML page. Default: DIR/report.html.", show_default=False),
    csv_path: Path = typer.Option(None, "--csv", help="The CSV. Default: DIR/report.csv.", show_default=False),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress lines and no closing line on stderr."),
) -> None:
    """Look at the latest batch in DIR: a self-contained HTML page (thumbnails inlined, the table
    sortable by its headers) and a CSV, one row per input — status and reason, error against its
    data (register: distance of the scan's points to the fit, in the scan's units; render: degrees
    between the map's normals and the fit's), landmark error, the pose search's ambiguity, hair
    share, seconds. Failures, files that cannot be checked and outliers (mean error above median +
    3·MAD) come first; the page's address may sort it, e.g. report.html#sort=-error_mean.
    Exit code 0 when the report is written, even for a batch with failures. Examples:

        \b
        statfit batch report fits/
        statfit batch report fits/ --out review/fits.html --csv review/fits.csv
    """
    from statfit.batch.report import csv_text, read_batch, report_rows
    from statfit.batch.report_page import report_html
    from statfit.io.files import check_writable, write_atomic

    batch = read_batch(out_dir)
    page, table = out or out_dir / "report.html", csv_path or out_dir / "report.csv"
    for target in (page, table):
        check_writable(target)
    started = last = time.perf_counter()

    def progress(done: int, total: int) -> None:
        nonlocal last
        now = time.perf_counter()
        if not quiet and (now - last >= PROGRESS_LINE_SECONDS or (done == total and now - started >= 1.0)):
            last = now
            print(f"statfit: report: {done}/{total} inputs checked, {now - started:.0f} s", file=sys.stderr, flush=True)

    rows = report_rows(batch, progress)
    write_atomic(table, csv_text(rows).encode())
    write_atomic(page, report_html(batch, rows).encode())
    if not quiet:
        failed = sum(row.status == "failed" for row in rows)
        outliers = sum(row.outlier for row in rows)
        print(f"statfit: report: {len(rows)} inputs ({failed} failed, {outliers} outliers) → {page}, {table}",
              file=sys.stderr)

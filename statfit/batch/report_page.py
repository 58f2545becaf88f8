"""The batch report as one self-contained HTML page: thumbnails inlined as PNG data URIs, the table
sortable by clicking its headers (inline script, nothing fetched). ``#sort=COLUMN`` in the page's
address sorts it on opening (``#sort=-COLUMN``: descending), e.g. ``report.html#sort=-seconds``."""
from __future__ import annotations

import base64
import html
from collections.abc import Callable
from typing import Any

from statfit.batch.report import OUTLIER_MADS, Batch, ReportRow
from statfit.renderer.images import FAR_SHARE

# Each <img> is marked data-loaded="1" once it has decoded to a picture, "0" if it failed.
MARK_IMAGES_JS = """
for (const img of document.images) {
  const mark = () => { img.dataset.loaded = img.naturalWidth > 0 ? "1" : "0"; };
  if (img.complete) mark(); else { img.addEventListener("load", mark); img.addEventListener("error", mark); }
}
"""

SORT_JS = """
const table = document.getElementById("rows");
const headers = Array.from(table.tHead.rows[0].cells);
function sortBy(th, ascending) {
  const col = headers.indexOf(th), body = table.tBodies[0];
  const key = r => r.cells[col].dataset.sort ?? r.cells[col].textContent.trim();
  const rows = Array.from(body.rows).sort((a, b) => {
    const x = key(a), y = key(b);
    if (x === "" || y === "") return (x === "") - (y === "");   // missing values last either way
    const nx = Number(x), ny = Number(y);
    const c = isNaN(nx) || isNaN(ny) ? x.localeCompare(y) : nx - ny;
    return ascending ? c : -c;
  });
  headers.forEach(h => h.removeAttribute("data-order"));
  th.dataset.order = ascending ? "asc" : "desc";
  rows.forEach(r => body.appendChild(r));
}
headers.forEach(th => th.addEventListener("click", () => sortBy(th, th.dataset.order !== "asc")));
const wanted = /^#sort=(-?)([\\w-]+)$/.exec(location.hash);
const start = wanted && headers.find(h => h.dataset.column === wanted[2]);
if (start) sortBy(start, wanted[1] !== "-");
"""

STYLE = """
body { font: 14px system-ui, sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; }
th, td { border-bottom: 1px solid #ddd; padding: 4px 8px; text-align: left; vertical-align: middle; }
th { cursor: pointer; background: #f3f3f3; position: sticky; top: 0; user-select: none; }
th[data-order=asc]::after { content: " ▲"; } th[data-order=desc]::after { content: " ▼"; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.failed td { background: #fde8e8; } tr.unchecked td { background: #fff1dc; }
tr.outlier td { background: #fff8c4; } tr.pending td { color: #888; }
.reason { max-width: 28em; white-space: normal; }
"""


def _fmt(value: float | None, digits: str = ".4g", scale: float = 1.0) -> str:
    return "" if value is None else format(value * scale, digits)


def _cell(text: str, sort: Any = None, css: str = "") -> str:
    sort_attr = "" if sort is None else f' data-sort="{html.escape(str(sort))}"'
    css_attr = f' class="{css}"' if css else ""
    return f"<td{css_attr}{sort_attr}>{text}</td>"


def _number(value: float | None, digits: str = ".4g", scale: float = 1.0) -> str:
    return _cell(_fmt(value, digits, scale), "" if value is None else repr(value), "num")


def _residual(row: ReportRow) -> str:
    """register's default: its fit's mean distance to the scan in model radii, and whether it fell back."""
    text = _fmt(row.fit_residual, ".2%") + (", fell back" if row.fell_back else "")
    return _cell(html.escape(text), "" if row.fit_residual is None else repr(row.fit_residual), "num")


def _thumbnail(row: ReportRow) -> str:
    if row.thumbnail is None:
        return _cell("—", "")
    data = base64.b64encode(row.thumbnail).decode("ascii")
    return _cell(f'<img src="data:image/png;base64,{data}" alt="fit of {html.escape(row.input)}">', "")


def _pose(row: ReportRow) -> str:
    if row.pose_ambiguous is None:
        return _cell("", "")
    scores = f"{_fmt(row.pose_runner_up, '.3f')}/{_fmt(row.pose_score, '.3f')}"
    text = f"{'ambiguous' if row.pose_ambiguous else 'clear'} ({scores})"
    return _cell(html.escape(text), int(row.pose_ambiguous))


def _row_class(row: ReportRow) -> str:
    return ["failed", "unchecked", "outlier", "pending", "ok"][row.attention]


COLUMNS: tuple[tuple[str, str, Callable[[ReportRow], str]], ...] = (
    ("fit", "fit over its data", _thumbnail),
    ("input", "input", lambda r: _cell(f'<span title="{html.escape(r.input)}">'
                                       f'{html.escape(r.output or r.input)}</span>')),
    ("status", "status", lambda r: _cell(html.escape(r.status + (" · outlier" if r.outlier else "")))),
    ("reason", "reason", lambda r: _cell(html.escape(r.reason), css="reason")),
    ("error_mean", "mean error", lambda r: _number(r.error_mean)),
    ("error_median", "median error", lambda r: _number(r.error_median)),
    ("landmark_error", "landmark error", lambda r: _number(r.landmark_error)),
    ("pose", "pose (runner-up/best)", _pose),
    ("hair_share", "hair share", lambda r: _number(r.hair_share, ".1%")),
    ("fit_residual", "fit residual", _residual),
    ("seconds", "seconds", lambda r: _number(r.seconds, ".1f")),
)


def report_html(batch: Batch, rows: list[ReportRow]) -> str:
    """The page: a heading that counts the rows by status, what the columns mean, and the table."""
    counts = {name: sum(row.attention == rank for row in rows)
              for rank, name in enumerate(("failed", "not checkable", "outliers", "pending", "fine"))}
    unit = "degrees between the map's normals and the fit's, over the pixels both cover" \
        if batch.command == "render" else "distance of the scan's points to the fitted surface, in the scan's units"
    view = ("the target normal map beside the fit's" if batch.command == "render" else
            f"the fit from its front, with the scan's points it does not hide: green on its surface, red "
            f"{FAR_SHARE:.0%} of its radius or more off")
    head = "".join(f'<th data-column="{key}">{html.escape(title)}</th>' for key, title, _ in COLUMNS)
    body = "\n".join(f'<tr class="{_row_class(row)}" data-input="{html.escape(row.input)}" '
                     f'data-status="{row.status}">' + "".join(render(row) for _, _, render in COLUMNS) + "</tr>"
                     for row in rows)
    summary = ", ".join(f"{count} {name}" for name, count in counts.items() if count)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>statfit batch report: {html.escape(str(batch.out_dir))}</title>
<style>{STYLE}</style></head>
<body>
<h1>statfit batch {html.escape(batch.command)}: {html.escape(str(batch.out_dir))}</h1>
<p>{len(rows)} input{'' if len(rows) == 1 else 's'}: {html.escape(summary)}. Failures, rows whose files cannot
be checked and outliers (mean error above the median + {OUTLIER_MADS:g}·MAD of the batch) come first; click a
header to sort.</p>
<p>Error: {html.escape(unit)}. Thumbnail: {html.escape(view)}.</p>
<table id="rows"><thead><tr>{head}</tr></thead>
<tbody>
{body}
</tbody></table>
<script>{MARK_IMAGES_JS}{SORT_JS}</script>
</body></html>
"""

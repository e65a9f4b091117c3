# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse compare --html`: one self-contained HTML file of a comparison.

The table, the notes on its columns, every plot (PNG embedded as a base64 `data:` URI) and
the effective config, with inline CSS only: no script, no stylesheet or image fetched from
anywhere, so the file opens offline and can be sent on its own.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import TYPE_CHECKING

from uwbfuse import __version__

if TYPE_CHECKING:
    from uwbfuse.compare import CompareResult

_CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1700px; padding: 0 1em;
       color: #222; }
table { border-collapse: collapse; font-size: 0.9em; margin: 1em 0; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; }
td.text { text-align: left; max-width: 40em; }
td.method { text-align: left; font-weight: bold; }
span.swatch { display: inline-block; width: 1.6em; height: 0.6em; margin-right: 0.4em; }
figure { margin: 1.5em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
pre { background: #f6f6f6; padding: 1em; overflow-x: auto; font-size: 0.85em; }
p.note { font-size: 0.9em; color: #444; }
"""
_TEXT_COLUMNS = {"status", "error"}


def _table(result: CompareResult) -> str:
    from uwbfuse.compare import COLUMNS
    from uwbfuse.plots import method_color

    head = "".join(f"<th>{html.escape(c)}</th>" for c in COLUMNS)
    body = []
    for row in result.rows:
        cells = row.cells()
        tds = []
        for c in COLUMNS:
            value = html.escape(cells[c])
            if c == "method":
                swatch = f'<span class="swatch" style="background:{method_color(row.method)}">'
                tds.append(f'<td class="method">{swatch}</span>{value}</td>')
            else:
                cls = ' class="text"' if c in _TEXT_COLUMNS else ""
                tds.append(f"<td{cls}>{value}</td>")
        body.append("<tr>" + "".join(tds) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>\n" + "\n".join(body) + \
        "\n</tbody></table>"


def _figure(png: Path) -> str:
    data = base64.b64encode(png.read_bytes()).decode("ascii")
    name = html.escape(png.name)
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{name}">'
            f"<figcaption>{name}</figcaption></figure>")


def render_html(result: CompareResult, plots: list[Path], config_text: str) -> str:
    """The report as one HTML string (plots read from `plots`, PNG files)."""
    title = f"uwbfuse compare: {result.log_path}"
    notes = "".join(f'<p class="note">{html.escape(n)}</p>' for n in result.notes())
    figures = "\n".join(_figure(p) for p in plots if p.suffix == ".png")
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{html.escape(title)}</title>
<style>{_CSS}</style>
</head>
<body>
<h1>{html.escape(title)}</h1>
<p>uwbfuse {html.escape(__version__)}; positions in the map frame, metres; errors against
the ground truth.</p>
<h2>Results</h2>
{_table(result)}
{notes}
<h2>Plots</h2>
{figures}
<h2>Effective config</h2>
<pre>{html.escape(config_text)}</pre>
</body>
</html>
"""


def write_html_report(
    path: Path, result: CompareResult, plots: list[Path], config_text: str
) -> Path:
    """Write `render_html(...)` to `path` whole or not at all; returns `path`."""
    from uwbfuse.compare import write_text_atomic

    write_text_atomic(path, render_html(result, plots, config_text))
    return path

"""Render a report as one self-contained HTML file: inline CSS, figures as base64 PNG.

Nothing is fetched when the page is opened (no scripts, fonts, stylesheets or images from
elsewhere). Every number is a ``<span class="num" data-key=... data-value=...>``.
"""

from __future__ import annotations

import base64
from collections.abc import Mapping
from html import escape

from app.report.content import (
    Block,
    Bullets,
    Cell,
    FigureRef,
    Heading,
    KeyValues,
    Num,
    Para,
    Pre,
    Signature,
    Table,
    Verdict,
)

CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;color:#1b1b1b;
 max-width:1000px;margin:24px auto;padding:0 20px;background:#fff}
h1{font-size:24px;border-bottom:3px solid #1f5fa8;padding-bottom:6px;margin-bottom:12px}
h2{font-size:19px;color:#1f5fa8;border-bottom:1px solid #ccd;margin-top:30px;padding-bottom:3px}
h3{font-size:15px;margin:18px 0 6px}
table{border-collapse:collapse;margin:8px 0 14px;font-size:13px}
th,td{border:1px solid #d4d7de;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#eef1f6;font-weight:600}
table.kv th{width:230px;background:#f6f7f9;font-weight:500;color:#333}
td .num,.num{font-family:ui-monospace,'DejaVu Sans Mono',Menlo,Consolas,monospace;
 white-space:nowrap}
td.n{text-align:right}
td.flag{background:#ffe3a3;font-weight:700}
caption{caption-side:top;text-align:left;font-weight:600;padding:4px 0;color:#333}
.verdict{border-left:6px solid;padding:10px 16px;margin:8px 0 16px;border-radius:3px}
.verdict.consistent{border-color:#2b8a3e;background:#ebf7ee}
.verdict.review{border-color:#c92a2a;background:#fdecec}
.verdict .headline{font-size:17px;font-weight:700;margin-bottom:4px}
figure{margin:12px 0 22px}
figure img{max-width:100%;border:1px solid #e3e5ea}
figcaption{font-size:13px;color:#444;margin-top:3px}
pre{background:#f6f7f9;border:1px solid #e3e5ea;padding:8px;font-size:12px;overflow:auto}
.sign{margin-top:36px;border:1px solid #99a;padding:14px 18px}
.sign td{border:none;padding:14px 10px 2px 0}
.sign .line{display:inline-block;border-bottom:1px solid #333;width:260px}
@media print{body{margin:0;max-width:none}h2{page-break-after:avoid}figure{page-break-inside:avoid}}
"""


def _cell(c: Cell) -> str:
    if isinstance(c, Num):
        return (f'<span class="num" data-key="{escape(c.key)}" data-value="{c.value!r}">'
                f"{escape(c.text)}</span>")
    return escape(c)


def _td_class(c: Cell, flagged: bool) -> str:
    return " ".join(k for k, on in (("n", isinstance(c, Num)), ("flag", flagged)) if on)


def _block(b: Block, images: Mapping[str, bytes]) -> str:
    if isinstance(b, Heading):
        return f"<h{b.level}>{escape(b.text)}</h{b.level}>"
    if isinstance(b, Para):
        return f"<p>{escape(b.text)}</p>"
    if isinstance(b, Bullets):
        return "<ul>" + "".join(f"<li>{escape(t)}</li>" for t in b.items) + "</ul>"
    if isinstance(b, KeyValues):
        rows = "".join(f"<tr><th>{escape(k)}</th><td>{''.join(_cell(c) for c in v)}</td></tr>"
                       for k, v in b.rows)
        return f'<table class="kv">{rows}</table>'
    if isinstance(b, Table):
        cap = f"<caption>{escape(b.caption)}</caption>" if b.caption else ""
        head = "".join(f"<th>{escape(c)}</th>" for c in b.columns)
        body = "".join(
            "<tr>" + "".join(
                f'<td class="{_td_class(c, (i, j) in b.flagged)}">{_cell(c)}</td>'
                for j, c in enumerate(row)) + "</tr>"
            for i, row in enumerate(b.rows))
        return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    if isinstance(b, Verdict):
        lines = "".join(f"<li>{escape(t)}</li>" for t in b.lines)
        return (f'<div class="verdict {escape(b.status)}" id="verdict" '
                f'data-status="{escape(b.status)}"><div class="headline">'
                f"{escape(b.headline)}</div><ul>{lines}</ul></div>")
    if isinstance(b, FigureRef):
        data = base64.b64encode(images[b.key]).decode("ascii")
        return (f'<figure id="fig-{escape(b.key)}"><img alt="{escape(b.caption)}" '
                f'src="data:image/png;base64,{data}"><figcaption>{escape(b.caption)}'
                "</figcaption></figure>")
    if isinstance(b, Pre):
        return f"<h3>{escape(b.title)}</h3><pre>{escape(b.text)}</pre>"
    if isinstance(b, Signature):
        line = '<span class="line">&nbsp;</span>'
        return ('<div class="sign"><strong>Review and approval</strong><table>'
                f"<tr><td>Reviewed by (name)</td><td>{line}</td></tr>"
                f"<tr><td>Date</td><td>{line}</td></tr>"
                f"<tr><td>Signature</td><td>{line}</td></tr></table></div>")
    raise TypeError(f"unknown block {b!r}")


def render_html(blocks: list[Block], images: Mapping[str, bytes], title: str) -> str:
    """The complete HTML document of ``blocks`` with ``images`` (key -> PNG bytes) inlined."""
    body = "\n".join(_block(b, images) for b in blocks)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>{escape(title)}</title><style>{CSS}</style></head>\n<body>\n{body}\n"
            "</body></html>\n")

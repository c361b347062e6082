"""Render a report as a PDF (matplotlib PdfPages, A4 portrait, no system dependencies).

The same blocks as the HTML, laid out top to bottom: text and tables (monospace cells), the
verdict box, the figures (PNG) scaled to the page width, a footer with page i/N.
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Callable, Mapping

import matplotlib.image as mpimg
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

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

PAGE_W, PAGE_H = 8.27, 11.69  # inches (A4)
MARGIN = 0.6
TOP, BOTTOM = PAGE_H - MARGIN, MARGIN + 0.3
WIDTH = PAGE_W - 2 * MARGIN
BODY, MONO = 8.5, 7.2  # font sizes (pt)
MONO_ADVANCE = 0.602  # DejaVu Sans Mono advance width (em)
VERDICT_COLORS = {"consistent": ("#2b8a3e", "#ebf7ee"), "review": ("#c92a2a", "#fdecec")}

Op = Callable[[Figure], None]


def _text(c: Cell) -> str:
    return c.text if isinstance(c, Num) else c


class _Layout:
    """Places blocks on pages; ``pages`` holds the drawing operations of each page."""

    def __init__(self) -> None:
        self.pages: list[list[Op]] = [[]]
        self.y = TOP

    def need(self, height: float) -> None:
        if self.y - height < BOTTOM and self.pages[-1]:
            self.pages.append([])
            self.y = TOP

    def text(self, x: float, s: str, size: float, *, weight: str = "normal",
             family: str = "sans-serif", color: str = "#1b1b1b", height: float | None = None,
             bg: str | None = None) -> None:
        h = height if height is not None else size * 1.45 / 72
        self.need(h)
        y = self.y

        def op(fig: Figure, x: float = x, y: float = y, s: str = s) -> None:
            kw = {"bbox": {"facecolor": bg, "edgecolor": "none", "pad": 1.0}} if bg else {}
            fig.text(x / PAGE_W, y / PAGE_H, s, fontsize=size, fontweight=weight,
                     family=family, color=color, va="top", ha="left", **kw)
        self.pages[-1].append(op)
        self.y -= h

    def gap(self, inches: float) -> None:
        self.y -= inches

    def wrapped(self, x: float, s: str, size: float = BODY, width_in: float = WIDTH,
                **kw: object) -> None:
        chars = max(int(width_in * 72 / (size * 0.52)), 20)
        for line in textwrap.wrap(s, chars) or [""]:
            self.text(x, line, size, **kw)  # type: ignore[arg-type]

    def op(self, height: float, draw: Callable[[Figure, float], None]) -> None:
        self.need(height)
        y = self.y
        self.pages[-1].append(lambda fig: draw(fig, y))
        self.y -= height


def _table(lay: _Layout, b: Table) -> None:
    cells = [list(b.columns)] + [[_text(c) for c in row] for row in b.rows]
    widths = [max(len(r[j]) for r in cells) for j in range(len(b.columns))]
    char = MONO_ADVANCE * MONO / 72
    starts, pos = [], 0
    for w in widths:
        starts.append(pos)
        pos += w + 2
    size = MONO if pos * char <= WIDTH else MONO * WIDTH / (pos * char)
    char = MONO_ADVANCE * size / 72
    numeric = [j > 0 and all(r[j][:1] in "-0123456789n" for r in cells[1:])
               for j in range(len(widths))]
    line = size * 1.5 / 72
    caption = BODY * 1.45 / 72 if b.caption else 0.0
    lay.need(caption + line * min(len(cells), 4))  # no orphaned caption or header
    if b.caption:
        lay.text(MARGIN, b.caption, BODY, weight="bold")

    def row_ops(i: int, row: list[str]) -> None:
        for j, s in enumerate(row):
            flagged = i > 0 and (i - 1, j) in b.flagged
            text = s.rjust(widths[j]) if numeric[j] else s
            lay.pages[-1].append(_cell_op(MARGIN + starts[j] * char, lay.y, text, size,
                                          i == 0, flagged))
        lay.y -= line
        if i == 0:
            y = lay.y + size * 0.25 / 72
            lay.pages[-1].append(lambda fig, y=y, w=pos * char: fig.add_artist(Rectangle(
                (MARGIN / PAGE_W, y / PAGE_H), w / PAGE_W, 0.6 / 72 / PAGE_H,
                transform=fig.transFigure, color="#888")))

    row_ops(0, cells[0])
    for i, row in enumerate(cells[1:], start=1):
        if lay.y - line < BOTTOM:
            lay.need(2 * line)
            row_ops(0, cells[0])  # repeat the header on the new page
        row_ops(i, row)
    lay.gap(0.08)


def _cell_op(x: float, y: float, s: str, size: float, head: bool, flagged: bool) -> Op:
    def op(fig: Figure) -> None:
        kw = {"bbox": {"facecolor": "#ffe3a3", "edgecolor": "none", "pad": 0.8}} if flagged \
            else {}
        fig.text(x / PAGE_W, y / PAGE_H, s, fontsize=size, family="monospace", va="top",
                 fontweight="bold" if head or flagged else "normal", **kw)
    return op


def _keyvalues(lay: _Layout, b: KeyValues) -> None:
    label_w = 2.15
    for key, row in b.rows:
        value = "".join(_text(c) for c in row)
        lines = textwrap.wrap(value, int((WIDTH - label_w) * 72 / (BODY * 0.5))) or [""]
        labels = textwrap.wrap(key, int((label_w - 0.1) * 72 / (BODY * 0.56))) or [""]
        n = max(len(lines), len(labels))
        lay.need(n * BODY * 1.45 / 72)
        y0 = lay.y
        for label in labels:
            lay.text(MARGIN, label, BODY, weight="bold", color="#333")
        lay.y = y0
        for line in lines:
            lay.text(MARGIN + label_w, line, BODY)
        lay.y = y0 - n * BODY * 1.45 / 72
    lay.gap(0.08)


def _verdict(lay: _Layout, b: Verdict) -> None:
    edge, fill = VERDICT_COLORS.get(b.status, ("#555", "#f3f3f3"))
    chars = int((WIDTH - 0.4) * 72 / (BODY * 0.52))
    lines = [ln for t in b.lines for ln in textwrap.wrap("• " + t, chars)]
    height = (13 * 1.5 + len(lines) * BODY * 1.45) / 72 + 0.2

    def box(fig: Figure, y: float) -> None:
        fig.add_artist(Rectangle((MARGIN / PAGE_W, (y - height) / PAGE_H), WIDTH / PAGE_W,
                                 height / PAGE_H, transform=fig.transFigure, facecolor=fill,
                                 edgecolor="none"))
        fig.add_artist(Rectangle((MARGIN / PAGE_W, (y - height) / PAGE_H), 0.08 / PAGE_W,
                                 height / PAGE_H, transform=fig.transFigure, facecolor=edge,
                                 edgecolor="none"))
    lay.need(height)
    lay.op(0.0, box)
    lay.gap(0.1)
    lay.text(MARGIN + 0.25, b.headline, 13, weight="bold", color=edge)
    for ln in lines:
        lay.text(MARGIN + 0.25, ln, BODY)
    lay.gap(0.2)


def _figure(lay: _Layout, b: FigureRef, png: bytes) -> None:
    img = mpimg.imread(io.BytesIO(png), format="png")
    h_px, w_px = img.shape[:2]
    width = WIDTH
    height = width * h_px / w_px
    cap = BODY * 1.6 / 72
    if height + cap > TOP - BOTTOM:
        height = TOP - BOTTOM - cap
        width = height * w_px / h_px
    lay.need(height + cap)
    lay.text(MARGIN, b.caption, BODY, weight="bold")

    def draw(fig: Figure, y: float) -> None:
        ax = fig.add_axes((MARGIN / PAGE_W, (y - height) / PAGE_H, width / PAGE_W,
                           height / PAGE_H))
        ax.imshow(img, interpolation="antialiased")
        ax.set_axis_off()
    lay.op(height + 0.15, draw)


def _signature(lay: _Layout) -> None:
    lay.need(1.6)
    lay.gap(0.15)
    lay.text(MARGIN, "Review and approval", 11, weight="bold")
    for label in ("Reviewed by (name)", "Date", "Signature"):
        lay.gap(0.18)
        y = lay.y
        lay.text(MARGIN, label, BODY)
        lay.pages[-1].append(lambda fig, y=y: fig.add_artist(Rectangle(
            ((MARGIN + 1.6) / PAGE_W, (y - 0.16) / PAGE_H), 3.2 / PAGE_W, 0.8 / 72 / PAGE_H,
            transform=fig.transFigure, color="#333")))


def layout(blocks: list[Block], images: Mapping[str, bytes]) -> list[list[Op]]:
    """Drawing operations per page."""
    lay = _Layout()
    for b in blocks:
        if isinstance(b, Heading):
            size = {1: 16, 2: 12.5, 3: 10}.get(b.level, 10)
            lay.need(size * 4 / 72)  # keep a heading with what follows
            lay.gap(0.12 if b.level > 1 else 0)
            lay.text(MARGIN, b.text, size, weight="bold",
                     color="#1f5fa8" if b.level == 2 else "#1b1b1b")
            lay.gap(0.04)
        elif isinstance(b, Para):
            lay.wrapped(MARGIN, b.text)
            lay.gap(0.06)
        elif isinstance(b, Bullets):
            for item in b.items:
                chars = int((WIDTH - 0.2) * 72 / (BODY * 0.52))
                for k, ln in enumerate(textwrap.wrap(item, chars)):
                    lay.text(MARGIN + (0.05 if k == 0 else 0.2), ("• " if k == 0 else "") + ln,
                             BODY)
            lay.gap(0.06)
        elif isinstance(b, KeyValues):
            _keyvalues(lay, b)
        elif isinstance(b, Table):
            _table(lay, b)
        elif isinstance(b, Verdict):
            _verdict(lay, b)
        elif isinstance(b, FigureRef):
            _figure(lay, b, images[b.key])
        elif isinstance(b, Pre):
            lay.text(MARGIN, b.title, 10, weight="bold")
            for ln in b.text.splitlines():
                lay.text(MARGIN, ln[:120], MONO, family="monospace")
            lay.gap(0.08)
        elif isinstance(b, Signature):
            _signature(lay)
    return [p for p in lay.pages if p]


def render_pdf(blocks: list[Block], images: Mapping[str, bytes], footer: str) -> tuple[bytes, int]:
    """The PDF bytes of ``blocks`` and its page count."""
    pages = layout(blocks, images)
    buf = io.BytesIO()
    with PdfPages(buf, metadata={"Title": "Laser beam calibration report",
                                 "Creator": "lasercal report"}) as pdf:
        for i, ops in enumerate(pages):
            fig = Figure(figsize=(PAGE_W, PAGE_H))
            FigureCanvasAgg(fig)
            for op in ops:
                op(fig)
            fig.text(MARGIN / PAGE_W, (MARGIN - 0.05) / PAGE_H, footer, fontsize=7,
                     color="#666", va="bottom")
            fig.text((PAGE_W - MARGIN) / PAGE_W, (MARGIN - 0.05) / PAGE_H,
                     f"page {i + 1} / {len(pages)}", fontsize=7, color="#666", va="bottom",
                     ha="right")
            pdf.savefig(fig)
    return buf.getvalue(), len(pages)

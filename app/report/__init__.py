"""Calibration reports: one self-contained HTML file, a PDF of the same content, and the numbers
as JSON (the calibration file, ``solve --json`` plus a ``report`` block) and CSV (per pose).

Entry points: :func:`build_report_bytes` (the dashboard's **Download report** button and the
``lasercal report`` command) and :func:`write_report` (to a file or a directory).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

#: File names of a report bundle.
HTML_NAME, PDF_NAME, JSON_NAME, CSV_NAME = ("report.html", "report.pdf", "calibration.json",
                                            "residuals.csv")


def render_bundle(report: Any, formats: Sequence[str] = ("html", "pdf", "json", "csv")
                  ) -> dict[str, bytes]:
    """The files of a :class:`~app.report.data.Report` (name -> bytes) in the given formats."""
    import json

    from app.report.content import document
    from app.report.plots import figures, png_bytes

    out: dict[str, bytes] = {}
    blocks = document(report)
    if "html" in formats or "pdf" in formats:
        images = {}
        for key, _, fig in figures(report):
            images[key] = png_bytes(fig, dpi=110)
        if "html" in formats:
            from app.report.html import render_html

            out[HTML_NAME] = render_html(blocks, images, _title(report)).encode("utf-8")
        if "pdf" in formats:
            from app.report.pdf import render_pdf

            footer = (f"lasercal calibration report · {Path(str(report.meta['source'])).name} · "
                      f"sha256 {str(report.meta['sha256'])[:16]} · {report.meta['generated']}")
            out[PDF_NAME], _ = render_pdf(blocks, images, footer)
    if "json" in formats:
        out[JSON_NAME] = (json.dumps(report.json_dict(), indent=2) + "\n").encode("utf-8")
    if "csv" in formats:
        out[CSV_NAME] = residuals_csv(report).encode("utf-8")
    return out


def _title(report: Any) -> str:
    return f"Calibration report: {Path(str(report.meta['source'])).name}"


def residuals_csv(report: Any) -> str:
    """Per-pose residuals (mm, deg) as CSV; ``#`` comment lines name the source and units."""
    head = (f"# lasercal report residuals: source {report.meta['source']}, sha256 "
            f"{report.meta['sha256']}\n"
            "# e_* = eq-16 spot minus camera (x, y) and minus the plate (z), mm; spot_z of a "
            "schoenflies calibration is z_P - delta; chi2 = e^T C^-1 e with the noise model "
            "scaled by the variance factors\n")
    return head + report.poses.to_csv(index=False, float_format="%.9g")


def build_report_bytes(result: Any, dataset: Any, meta: Mapping[str, Any] | None = None,
                       sections: Sequence[Mapping[str, Any]] = ()) -> dict[str, bytes]:
    """``{'report.html', 'report.pdf', 'calibration.json', 'residuals.csv'} -> bytes``.

    ``result``: the :class:`~calib_core.calibrate.BeamCalibration` of ``solve(dataset, ...)``
    (the full data set, hold-out rows included). ``meta``: header fields, all optional —
    ``source``, ``sha256``, ``note``, ``created``, ``mode`` ('simulated'/'hardware'),
    ``drivers`` {device: driver}, ``software_recorded``, ``workcell`` (TOML text),
    ``workcell_source``, ``grid``, ``options`` {solve option: value}; for a session file
    :func:`app.report.data.source_meta` reads them all. ``sections``: optional application
    results (:func:`app.report.data.section_from_json`).
    """
    from app.report.data import build_report

    return render_bundle(build_report(result, dataset, meta, sections))


def write_report(files: Mapping[str, bytes], out: str | Path) -> list[Path]:
    """Write a bundle: ``out`` ending .html or .pdf gets that file, anything else is a directory
    that receives every file. Returns the paths written."""
    from calib_core.errors import InputError

    out = Path(out)
    suffix = out.suffix.lower()
    try:
        if suffix in (".html", ".htm", ".pdf"):
            name = PDF_NAME if suffix == ".pdf" else HTML_NAME
            if not out.parent.is_dir():
                raise InputError(f"{out}: directory {out.parent} does not exist")
            out.write_bytes(files[name])
            return [out]
        if out.exists() and not out.is_dir():
            raise InputError(f"{out}: exists and is not a directory (use a name ending .html "
                             "or .pdf for a single file)")
        out.mkdir(parents=True, exist_ok=True)
        written = []
        for name, data in files.items():
            (out / name).write_bytes(data)
            written.append(out / name)
        return written
    except OSError as exc:
        raise InputError(f"{out}: cannot write the report ({exc.strerror or exc})") from None

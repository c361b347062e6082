"""The report as an ordered list of blocks that both the HTML and the PDF renderer draw.

Blocks: :class:`Heading`, :class:`Para`, :class:`KeyValues`, :class:`Table`, :class:`Bullets`,
:class:`Verdict`, :class:`FigureRef`, :class:`Pre`, :class:`Signature`. Every number is a
:class:`Num` that carries its key (e.g. ``param.x_t.value``), the exact value and the text
shown, so tests can parse the rendering back and compare it with the solver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from app.report.data import Report
from app.report.plots import FIGURES

AXES = ("x", "y", "z")
SET_NAMES = {"fit": "fit set", "holdout": "hold-out set", "evaluated": "evaluated poses"}
#: Unit of each beam parameter.
UNITS = {"x_t": "mm", "y_t": "mm", "z_t": "mm", "z_t_minus_delta": "mm", "delta": "mm",
         "a": "-", "b": "-", "c": "-", "alpha": "slope", "beta": "slope"}
PARAM_MEANING = {
    "x_t": "beam point T, x (flange frame)", "y_t": "beam point T, y (flange frame)",
    "z_t": "beam point T, z (flange frame)",
    "z_t_minus_delta": "beam point T, z minus plate height delta",
    "a": "u' x (direction x gain)", "b": "u' y (direction x gain)",
    "c": "u' z (direction x gain)", "alpha": "plate tilt dz/dx", "beta": "plate tilt dz/dy",
    "delta": "plate height at x = y = 0",
}
CORRELATION_FLAG = 0.8


@dataclass(frozen=True)
class Num:
    """A number as shown (``text``) with its exact ``value`` and a stable ``key``."""

    key: str
    value: float
    text: str


Cell = str | Num


@dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2


@dataclass(frozen=True)
class Para:
    text: str


@dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]


@dataclass(frozen=True)
class KeyValues:
    rows: tuple[tuple[str, tuple[Cell, ...]], ...]


@dataclass(frozen=True)
class Table:
    columns: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]
    flagged: frozenset[tuple[int, int]] = field(default_factory=frozenset)
    caption: str = ""


@dataclass(frozen=True)
class Verdict:
    status: str
    headline: str
    lines: tuple[str, ...]


@dataclass(frozen=True)
class FigureRef:
    key: str
    caption: str


@dataclass(frozen=True)
class Pre:
    title: str
    text: str


@dataclass(frozen=True)
class Signature:
    pass


Block = Heading | Para | Bullets | KeyValues | Table | Verdict | FigureRef | Pre | Signature


def decimals_for(sigma: float, significant: int = 2) -> int:
    """Decimal places that show ``sigma`` with ``significant`` digits (0..10)."""
    if not (sigma > 0 and math.isfinite(sigma)):
        return 6
    return int(min(max(significant - 1 - math.floor(math.log10(sigma)), 0), 10))


def fixed(key: str, value: float, decimals: int) -> Num:
    """A number with a fixed count of decimals."""
    v = float(value)
    return Num(key, v, f"{v:.{decimals}f}" if math.isfinite(v) else "n/a")


def general(key: str, value: float, digits: int = 4) -> Num:
    """A number with ``digits`` significant digits, never in e-notation below 1e7."""
    v = float(value)
    if not math.isfinite(v):
        return Num(key, v, "n/a")
    if v == 0:
        return Num(key, v, "0")
    dec = max(digits - 1 - math.floor(math.log10(abs(v))), 0)
    return Num(key, v, f"{v:.{dec}f}")


def _header(report: Report) -> list[Block]:
    m, cal = report.meta, report.calibration
    robot = ("4-dof Schoenflies robot (rotations about z; 8 unknowns, z_t - delta)"
             if cal.model == "schoenflies" else "6-dof flange (9 unknowns)")
    what = (f"Laser displacement sensor beam H: point T and direction u' in the flange frame, "
            f"with the calibration plate; {robot}")
    rows: list[tuple[str, tuple[Cell, ...]]] = [
        ("What", (what,)),
        ("Data source", (f"{m['source']} ({m['kind']})",)),
        ("SHA-256 of the source", (m["sha256"] or "n/a",)),
        ("Recorded", (m.get("created") or "not recorded",)),
        ("Report generated", (str(m["generated"]),)),
        ("Operator note", (m.get("note") or "(none)",)),
        ("Hardware or simulated", (str(m.get("mode", "not recorded")),)),
        ("Workcell file", (m.get("workcell_source") or (
            "embedded in the session (see appendix)" if m.get("workcell") else "not recorded"),)),
    ]
    if m.get("grid"):
        rows.append(("Pose grid", (str(m["grid"]),)))
    drivers = m.get("drivers") or {}
    rows.append(("Drivers", ("; ".join(f"{k}: {v}" for k, v in drivers.items())
                             or "not recorded",)))
    rec = m.get("software_recorded") or {}
    if rec:
        rows.append(("Software at acquisition", (", ".join(f"{k} {v}" for k, v in rec.items()),)))
    rows.append(("Software (report)", (", ".join(f"{k} {v}" for k, v in m["versions"].items()),)))
    rows.append(("Calibration", (str(m.get("calibration_source", "")),)))
    opts = m.get("options") or {}
    if opts:
        rows.append(("Solve options", (", ".join(f"{k} = {v}" for k, v in opts.items()),)))
    rows.append(("Poses", (Num("n_points", cal.n_points, str(cal.n_points)), " in the data, ",
                           Num("n_used", cal.n_used, str(cal.n_used)),
                           " used in the fit" if report.mode == "solved" else " evaluated",
                           *((", ", Num("holdout.n", cal.holdout["n"], str(cal.holdout["n"])),
                              " held out") if cal.holdout else ()))))
    noise_cells: list[Cell] = []
    labels = {"camera": "camera x_p, y_p", "robot_xy": "robot x-y", "robot_z": "robot z",
              "robot_theta_deg": "robot rotation", "sensor": "sensor d"}
    for k, v in m["noise"].items():
        unit = "deg" if k.endswith("_deg") else "mm"
        noise_cells += ["; " if noise_cells else "", f"{labels.get(k, k)} ",
                        Num(f"noise.{k}", float(v), f"{float(v):g}"), f" {unit}"]
    rows.append(("Noise model (1-sigma)", tuple(noise_cells)))
    return [Heading(m.get("title", "Laser beam calibration report"), 1), KeyValues(tuple(rows))]


def _result(report: Report) -> list[Block]:
    cal = report.calibration
    sig = cal.sigma
    prow: list[tuple[Cell, ...]] = []
    for name, v, s in zip(cal.names, cal.values, sig, strict=True):
        dec = decimals_for(float(s))
        prow.append((name, fixed(f"param.{name}.value", v, dec), "±",
                     fixed(f"param.{name}.sigma", s, dec), UNITS.get(name, ""),
                     PARAM_MEANING.get(name, "")))
    blocks: list[Block] = [
        Heading("Result"),
        Table(("parameter", "value", "", "1-sigma", "unit", "meaning"), tuple(prow),
              caption="Beam H (names as in 'lasercal solve --json')"),
    ]
    gdec = decimals_for(cal.gain_sigma)
    u = cal.direction
    kv: list[tuple[str, tuple[Cell, ...]]] = [
        ("Gain |u'|", (fixed("gain.value", cal.gain, gdec), " ± ",
                       fixed("gain.sigma", cal.gain_sigma, gdec))),
        ("Beam direction u = u'/|u'|", ("(", fixed("direction.0", u[0], 6), ", ",
                                       fixed("direction.1", u[1], 6), ", ",
                                       fixed("direction.2", u[2], 6), ")")),
        ("Condition number", (general("condition_number", cal.condition_number, 4),)),
    ]
    sv: list[Cell] = []
    for k, v in enumerate(cal.singular_values):
        sv += [general(f"singular_value.{k}", v, 4), ", " if k < len(cal.singular_values) - 1
               else ""]
    kv.append(("Singular values (scaled, weighted)", tuple(sv) or ("n/a",)))
    kv.append(("Variance factors (1 = noise model confirmed)", (
        "lateral ", general("variance_factors.lateral", cal.variance_factors[0], 3),
        ", axial ", general("variance_factors.axial", cal.variance_factors[1], 3))))
    kv.append(("Reduced chi-square", (general("chi2_reduced", cal.chi2_reduced, 4),)))
    blocks.append(KeyValues(tuple(kv)))
    rho = cal.correlation
    names = cal.names
    crow: list[tuple[Cell, ...]] = []
    flagged: set[tuple[int, int]] = set()
    for j, a in enumerate(names):
        cells: list[Cell] = [a]
        for k, b in enumerate(names):
            cells.append(fixed(f"corr.{a}.{b}", rho[j, k], 3))
            if j != k and abs(rho[j, k]) > CORRELATION_FLAG:
                flagged.add((j, k + 1))
        crow.append(tuple(cells))
    blocks.append(Table(("", *names), tuple(crow), frozenset(flagged),
                        caption=f"Correlation matrix (|rho| > {CORRELATION_FLAG} flagged)"))
    return blocks


def _residuals(report: Report) -> list[Block]:
    rows: list[tuple[Cell, ...]] = []
    for label, stats in report.stats.items():
        exp = report.expected.get(label, {})
        ratios = report.verdict["ratios"].get(label, {})
        for axis in AXES:
            s = stats[axis]
            rows.append((SET_NAMES.get(label, label), axis,
                         fixed(f"resid.{label}.{axis}.mean_abs", s["mean_abs"], 4),
                         fixed(f"resid.{label}.{axis}.rms", s["rms"], 4),
                         fixed(f"resid.{label}.{axis}.max", s["max"], 4),
                         fixed(f"expected.{label}.{axis}", exp.get(axis, math.nan), 4),
                         fixed(f"ratio.{label}.{axis}", ratios.get(axis, math.nan), 2)))
    n = {k: int((report.poses["set"] == k).sum()) for k in ("fit", "holdout", "evaluated")}
    sizes = ", ".join(f"{SET_NAMES[k]}: {v} poses" for k, v in n.items() if v)
    blocks: list[Block] = [
        Heading("Residuals (seed Table 1 style, mm)"),
        Para("x, y: spot reconstructed by eq 16 minus the camera spot; z: reconstructed spot "
             "minus the fitted plate. 'Expected RMS' is the noise floor the noise model "
             f"predicts for these poses; {sizes}."),
        Table(("set", "axis", "mean abs", "RMS", "max", "expected RMS", "RMS / expected"),
              tuple(rows)),
        Heading("Outliers", 3),
    ]
    if not report.outliers:
        blocks.append(Para("No pose was excluded."
                           if report.mode == "solved" else
                           "Not applicable: the calibration was given, every pose is evaluated."))
    else:
        orow: list[tuple[Cell, ...]] = []
        for o in report.outliers:
            r = o["row"]
            orow.append((Num(f"outlier.{r}.row", r, str(r)), fixed(f"outlier.{r}.e_x", o["e_x"], 4),
                         fixed(f"outlier.{r}.e_y", o["e_y"], 4),
                         fixed(f"outlier.{r}.e_z", o["e_z"], 4),
                         fixed(f"outlier.{r}.chi2", o["chi2"], 1),
                         fixed(f"outlier.{r}.threshold", o["threshold"], 1)))
        blocks += [Table(("row", "e_x [mm]", "e_y [mm]", "e_z [mm]", "chi-square", "limit"),
                         tuple(orow)),
                   Bullets(tuple(f"row {o['row']}: {o['reason']}." for o in report.outliers))]
    blocks.append(Heading("Warnings", 3))
    if report.warnings:
        blocks.append(Bullets(tuple(f"{w} — {e}" for w, e in report.warnings)))
    else:
        blocks.append(Para("None."))
    return blocks


def _sections(report: Report) -> list[Block]:
    blocks: list[Block] = []
    for sec in report.sections:
        blocks.append(Heading(f"{sec['title']}"))
        blocks.append(Para(f"From {sec['source']}."))
        for t in sec.get("tables") or []:
            blocks.append(Table(tuple(t["columns"]), tuple(tuple(r) for r in t["rows"]),
                                caption=str(t.get("caption", ""))))
        if sec.get("rows"):
            blocks.append(KeyValues(tuple((k, (v,)) for k, v in sec["rows"])))
    return blocks


def document(report: Report) -> list[Block]:
    """Every block of the report, in reading order."""
    v = report.verdict
    blocks: list[Block] = _header(report)
    blocks += [Heading("Verdict"), Verdict(v["status"], v["headline"], tuple(v["lines"]))]
    blocks += _result(report)
    blocks += _residuals(report)
    blocks += _sections(report)
    blocks.append(Heading("Plots"))
    blocks += [FigureRef(key, caption) for key, caption, _ in FIGURES]
    appendix: list[Block] = []
    if report.meta.get("workcell"):
        appendix.append(Pre("Workcell file", str(report.meta["workcell"])))
    if report.meta.get("comments"):
        appendix.append(Pre("Comment lines of the data file", "\n".join(report.meta["comments"])))
    if appendix:
        blocks += [Heading("Appendix"), *appendix]
    blocks.append(Signature())
    return blocks


def numbers(blocks: list[Block]) -> dict[str, Any]:
    """key -> Num of every number in ``blocks`` (what a test parses back)."""
    out: dict[str, Any] = {}
    for b in blocks:
        cells: list[Any] = []
        if isinstance(b, KeyValues):
            cells = [c for _, row in b.rows for c in row]
        elif isinstance(b, Table):
            cells = [c for row in b.rows for c in row]
        for c in cells:
            if isinstance(c, Num):
                out[c.key] = c
    return out

"""Calibration reports: every number against the solver, HTML in Chromium, PDF pages, CLI errors.

Reports are rendered once per module (matplotlib is the slow part) from:
- the example paper-grid CSV with a 30 % hold-out;
- a simulated session file (.db) with a gross camera outlier, plus a platform campaign section;
- the session evaluated with the first report's calibration.json (``--calib``).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.cli import main
from app.commands.solve import load_calibration_data
from app.report import build_report_bytes
from app.report.data import build_report, expected_rms
from app.session import Sample, Session
from calib_core.calibrate import BeamCalibration, beam_residuals, solve
from calib_core.grid import paper_grid
from calib_core.noise import NoiseModel
from calib_core.stats import axis_statistics
from tests.core.simdata import as_dataset, seed_grid, seed_truth, simulate, tilted_grid

EXAMPLE = Path(__file__).resolve().parents[2] / "static_data" / "example_paper_grid.csv"
OUTLIER_ROW = 7
WORKCELL = "[cell]\nname = 'simulated seed cell'\n"


# ---- fixtures --------------------------------------------------------------------------------

def make_session(path: Path, seed: int = 3) -> Path:
    """A simulated session of the paper grid with a 0.5 mm camera mis-detection at pose 7."""
    grid = paper_grid()
    frame = simulate(seed_truth(), grid.poses, NoiseModel(), np.random.default_rng(seed),
                     outliers={OUTLIER_ROW: (0.5, 0.0)})
    with Session.create(path, grid, workcell_toml=WORKCELL, noise=NoiseModel().as_dict(),
                        drivers={"robot": "drivers.sim.devices.SimRobot",
                                 "sensor": "drivers.sim.devices.SimSensor"},
                        settings={"mode": "sim", "workcell_source": "static_data/x.toml"}
                        ) as s:
        for i, r in frame.iterrows():
            s.add_sample(Sample(int(i), grid.pose(int(i)),
                                (r["x_o"], r["y_o"], r["z_o"], r["theta_deg"]),
                                float(r["d"]), float(r["x_p"]), float(r["y_p"]), 0.9))
    return path


@pytest.fixture(scope="module")
def csv_report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("csv")
    src = root / "example_paper_grid.csv"
    shutil.copy(EXAMPLE, src)
    out = root / "out"
    assert main(["report", str(src), "--holdout", "0.3", "--note", "acceptance run 1",
                 "--out", str(out)]) == 0
    solved = solve(load_calibration_data(str(src)), holdout=0.3)
    return {"src": src, "out": out, "solved": solved}


@pytest.fixture(scope="module")
def session_report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("session")
    db = make_session(root / "cell.db")
    plat = root / "platform"
    assert main(["platform", "simulate", "--out", str(plat), "--seed", "1"]) == 0
    out = root / "out"
    assert main(["report", str(db), "--note", "night shift", "--platform", str(plat),
                 "--out", str(out)]) == 0
    solved = solve(load_calibration_data(str(db)))
    return {"src": db, "out": out, "solved": solved}


class NumParser(HTMLParser):
    """Collects ``<span class="num" data-key data-value>text</span>`` and all ``src``/``href``."""

    def __init__(self) -> None:
        super().__init__()
        self.nums: dict[str, tuple[float, str]] = {}
        self.links: list[str] = []
        self._key: str | None = None
        self._value = 0.0
        self.images = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        for name in ("src", "href"):
            if a.get(name):
                self.links.append(str(a[name]))
        if tag == "img":
            self.images += 1
        if "data-key" in a:
            self._key, self._value = str(a["data-key"]), float(str(a["data-value"]))

    def handle_data(self, data: str) -> None:
        if self._key is not None:
            assert self._key not in self.nums, f"duplicate key {self._key}"
            self.nums[self._key] = (self._value, data)
            self._key = None


def parse_html(path: Path) -> NumParser:
    p = NumParser()
    p.feed(path.read_text(encoding="utf-8"))
    return p


def shown_tolerance(text: str) -> float:
    """Half a unit of the last digit shown."""
    dec = len(text.split(".")[1]) if "." in text else 0
    return 0.5 * 10.0**-dec


def solver_numbers(d: dict) -> dict[str, float]:
    """key -> value of every solver number the report shows, from the ``solve --json`` object."""
    out: dict[str, float] = {"n_points": d["n_points"], "n_used": d["n_used"],
                             "gain.value": d["gain"], "gain.sigma": d["gain_sigma"],
                             "condition_number": d["condition_number"],
                             "chi2_reduced": d["chi2_reduced"],
                             "variance_factors.lateral": d["variance_factors"]["lateral"],
                             "variance_factors.axial": d["variance_factors"]["axial"]}
    for name, v in d["params"].items():
        out[f"param.{name}.value"] = v
        out[f"param.{name}.sigma"] = d["sigma"][name]
    for k, v in enumerate(d["direction"]):
        out[f"direction.{k}"] = v
    for k, v in enumerate(d["singular_values"]):
        out[f"singular_value.{k}"] = v
    names = d["covariance"]["names"]
    cov = np.array(d["covariance"]["matrix"])
    s = np.sqrt(np.diag(cov))
    for j, a in enumerate(names):
        for k, b in enumerate(names):
            out[f"corr.{a}.{b}"] = cov[j, k] / (s[j] * s[k])
    for label, block in (("fit", d["residuals"]),
                         ("holdout", (d.get("holdout") or {}).get("residuals", {}))):
        for axis, stats in block.items():
            for stat, v in stats.items():
                out[f"resid.{label}.{axis}.{stat}"] = v
    if d.get("holdout"):
        out["holdout.n"] = d["holdout"]["n"]
    for k, v in d["noise"].items():
        out[f"noise.{k}"] = v
    for r in d["outliers"]:
        out[f"outlier.{r}.row"] = r
    return out


def report_numbers(rep: dict) -> dict[str, float]:
    """Derived numbers from the report block of calibration.json (checked separately)."""
    out: dict[str, float] = {}
    for label, axes in rep["expected_rms"].items():
        for axis, v in axes.items():
            out[f"expected.{label}.{axis}"] = v
            out[f"ratio.{label}.{axis}"] = rep["verdict"]["ratios"][label][axis]
    for o in rep["outliers"]:
        for k in ("e_x", "e_y", "e_z", "chi2", "threshold"):
            out[f"outlier.{o['row']}.{k}"] = o[k]
    return out


def check_html_numbers(html: Path, expected: dict[str, float]) -> NumParser:
    parsed = parse_html(html)
    unchecked = sorted(set(parsed.nums) - set(expected))
    assert not unchecked, f"numbers in the HTML not checked: {unchecked}"
    missing = sorted(k for k in expected if k not in parsed.nums)
    assert not missing, f"solver numbers missing from the HTML: {missing}"
    for key, (value, text) in parsed.nums.items():
        want = expected[key]
        assert math.isclose(value, want, rel_tol=1e-12, abs_tol=1e-15), (key, value, want)
        assert abs(float(text) - want) <= shown_tolerance(text) * (1 + 1e-9) + 1e-15, \
            (key, text, want)
    return parsed


# ---- numbers ---------------------------------------------------------------------------------

def test_csv_report_numbers_match_the_solver(csv_report: dict) -> None:
    out, solved = csv_report["out"], csv_report["solved"]
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "report.html",
                                                      "report.pdf", "residuals.csv"]
    ref = solved.to_json_dict()
    doc = json.loads((out / "calibration.json").read_text())
    rep = doc.pop("report")
    assert json.dumps(doc, sort_keys=True) == json.dumps(ref, sort_keys=True)
    # the JSON is a calibration file
    back = BeamCalibration.from_json_dict(doc)
    np.testing.assert_array_equal(back.values, solved.values)
    expected = solver_numbers(ref) | report_numbers(rep)
    parsed = check_html_numbers(out / "report.html", expected)
    assert len(parsed.nums) > 100 and parsed.images == 5
    assert all(link.startswith("data:image/png;base64,") for link in parsed.links)
    html = (out / "report.html").read_text()
    assert "acceptance run 1" in html and hashlib.sha256(
        csv_report["src"].read_bytes()).hexdigest() in html
    assert "simulated (per file comment)" in html
    assert 'data-status="consistent"' in html
    assert rep["meta"]["sha256"] == hashlib.sha256(csv_report["src"].read_bytes()).hexdigest()
    assert rep["meta"]["versions"]["lasercal"] and rep["meta"]["note"] == "acceptance run 1"


def test_residual_csv_matches_the_model(csv_report: dict) -> None:
    solved = csv_report["solved"]
    data = load_calibration_data(str(csv_report["src"]))
    table = pd.read_csv(csv_report["out"] / "residuals.csv", comment="#")
    assert len(table) == 42 and list(table["row"]) == list(range(42))
    err = beam_residuals(data.poses, data.d, data.spot_xy, solved.values, solved.model)
    np.testing.assert_allclose(table[["e_x", "e_y", "e_z"]].to_numpy(), err, rtol=1e-7,
                               atol=1e-12)
    hold = set(solved.holdout["rows"])
    assert set(table.loc[table["set"] == "holdout", "row"]) == hold
    fit = table[table["set"] == "fit"]
    assert tuple(fit["row"]) == solved.rows_used
    stats = axis_statistics(fit[["e_x", "e_y", "e_z"]].to_numpy())
    for axis in "xyz":
        for stat in ("mean_abs", "rms", "max"):
            assert math.isclose(stats[axis][stat], solved.residuals[axis][stat], rel_tol=1e-6)


def test_session_report_lists_the_outlier_and_why(session_report: dict) -> None:
    out, solved = session_report["out"], session_report["solved"]
    assert solved.outliers == (OUTLIER_ROW,)
    ref = solved.to_json_dict()
    doc = json.loads((out / "calibration.json").read_text())
    rep = doc.pop("report")
    assert json.dumps(doc, sort_keys=True) == json.dumps(ref, sort_keys=True)
    check_html_numbers(out / "report.html", solver_numbers(ref) | report_numbers(rep))
    (o,) = rep["outliers"]
    assert o["row"] == OUTLIER_ROW and o["chi2"] > o["threshold"]
    assert abs(o["e_x"] + 0.5) < 0.02  # the spot was reported 0.5 mm too far in +x
    assert "camera mis-detection" in o["reason"]
    meta = rep["meta"]
    assert meta["mode"] == "simulated" and meta["kind"] == "session"
    assert meta["sha256"] == hashlib.sha256(session_report["src"].read_bytes()).hexdigest()
    assert meta["created"] and meta["drivers"]["robot"].endswith("SimRobot")
    html = (out / "report.html").read_text()
    for text in ("night shift", "simulated seed cell", "SimSensor", "Review and approval",
                 "Platform calibration", "ISO 9283", f"row {OUTLIER_ROW}:"):
        assert text in html, text
    table = pd.read_csv(out / "residuals.csv", comment="#")
    assert list(table.loc[table["set"] == "outlier", "row"]) == [OUTLIER_ROW]
    assert list(table["pose_index"]) == list(range(42))


def test_given_calibration_is_evaluated_not_refitted(csv_report: dict, session_report: dict,
                                                     tmp_path: Path) -> None:
    calib = csv_report["out"] / "calibration.json"
    out = tmp_path / "eval"
    assert main(["report", str(session_report["src"]), "--calib", str(calib),
                 "--out", str(out)]) == 0
    given = BeamCalibration.from_json_dict(json.loads(calib.read_text()))
    data = load_calibration_data(str(session_report["src"]))
    stats = axis_statistics(beam_residuals(data.poses, data.d, data.spot_xy, given.values,
                                           given.model))
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["params"] == json.loads(calib.read_text())["params"]
    parsed = parse_html(out / "report.html")
    for axis in "xyz":
        for stat in ("mean_abs", "rms", "max"):
            value, _ = parsed.nums[f"resid.evaluated.{axis}.{stat}"]
            assert math.isclose(value, stats[axis][stat], rel_tol=1e-12)
            assert math.isclose(doc["residuals"][axis][stat], stats[axis][stat], rel_tol=1e-12)
    assert not any(k.startswith("resid.fit") for k in parsed.nums)
    # the outlier row is evaluated like any other, so the review flag goes up
    assert doc["report"]["verdict"]["status"] == "review"


def test_minimal_calibration_file_and_measure_section(csv_report: dict, tmp_path: Path) -> None:
    """A hand-written calibration (model, params, sigma only) and a measure result section."""
    ref = csv_report["solved"].to_json_dict()
    calib = tmp_path / "H.json"
    calib.write_text(json.dumps({k: ref[k] for k in ("model", "params", "sigma")}))
    plane = tmp_path / "plane.json"
    plane.write_text(json.dumps({"alpha": 1.5e-3, "beta": -2.5e-3, "offset": 0.125,
                                 "normal": [0.0015, -0.0025, 1.0], "rms": 0.0042,
                                 "n_points": 25, "sigma": {"alpha": 1e-4, "beta": 2e-4,
                                                           "offset": 0.003}}))
    out = tmp_path / "r"
    assert main(["report", str(csv_report["src"]), "--calib", str(calib), "--measure",
                 str(plane), "--out", str(out)]) == 0
    text = (out / "calibration.json").read_text()
    doc = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    (section,) = doc["report"]["sections"]
    assert section["title"] == "Plane identification"
    assert dict(section["rows"])["sigma.offset"] == "0.003"
    html = (out / "report.html").read_text()
    assert "Plane identification" in html and "0.125" in html
    assert doc["condition_number"] is None and doc["report"]["meta"]["calibration_mode"] == \
        "evaluated"


def test_six_dof_data_single_file_outputs(tmp_path: Path) -> None:
    """General model (quaternions): --out FILE.html and --out FILE.pdf write just that file."""
    rng = np.random.default_rng(8)
    grid, q = tilted_grid(rng)
    src = tmp_path / "six.csv"
    simulate(seed_truth(delta=1.5), grid, NoiseModel(), rng, quaternions=q).to_csv(src,
                                                                                   index=False)
    assert main(["report", str(src), "--out", str(tmp_path / "six.html")]) == 0
    assert main(["report", str(src), "--out", str(tmp_path / "six.pdf")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["six.csv", "six.html", "six.pdf"]
    ref = solve(load_calibration_data(str(src))).to_json_dict()
    assert ref["model"] == "general"
    parsed = parse_html(tmp_path / "six.html")
    numbers = solver_numbers(ref)
    assert {"param.z_t.value", "param.delta.sigma"} <= set(parsed.nums)
    for key, (value, text) in parsed.nums.items():
        if key in numbers:
            assert math.isclose(value, numbers[key], rel_tol=1e-12, abs_tol=1e-15), key
            assert abs(float(text) - numbers[key]) <= shown_tolerance(text) * (1 + 1e-9)
    assert (tmp_path / "six.pdf").read_bytes().startswith(b"%PDF")


# ---- the noise floor -------------------------------------------------------------------------

def test_expected_rms_matches_simulated_scatter() -> None:
    """Observed/expected residual RMS averages 1 (within 8 %) over 15 simulated data sets."""
    rng = np.random.default_rng(11)
    ratios = {"fit": [], "holdout": []}
    for k in range(15):
        data = as_dataset(simulate(seed_truth(), seed_grid(), NoiseModel(), rng))
        res = solve(data, holdout=0.3, seed=k)
        sets = np.array(["holdout" if r in res.holdout["rows"] else "fit" for r in data.rows])
        exp = expected_rms(res, data, np.flatnonzero(sets == "fit"),
                           np.flatnonzero(sets == "holdout"))
        ratios["fit"].append([res.residuals[a]["rms"] ** 2 / exp["fit"][a] ** 2 for a in "xyz"])
        ratios["holdout"].append([res.holdout["residuals"][a]["rms"] ** 2
                                  / exp["holdout"][a] ** 2 for a in "xyz"])
    fit_ms = np.mean(ratios["fit"], axis=0)
    hold_ms = np.mean(ratios["holdout"], axis=0)
    assert np.all(np.abs(np.sqrt(fit_ms) - 1) < 0.08), fit_ms
    assert np.all(np.abs(np.sqrt(hold_ms) - 1) < 0.15), hold_ms


def test_verdict_flags_residuals_above_the_noise_floor() -> None:
    rng = np.random.default_rng(5)
    data = as_dataset(simulate(seed_truth(), seed_grid(), NoiseModel(), rng,
                               noise_scale=(3.0, 1.0)))
    report = build_report(solve(data), data, {"source": "sim"})
    assert report.verdict["status"] == "review"
    assert report.verdict["ratios"]["fit"]["x"] > 2.0
    assert any("exceed the noise floor" in line for line in report.verdict["lines"])


# ---- the dashboard entry point ---------------------------------------------------------------

def test_build_report_bytes_for_the_dashboard() -> None:
    data = as_dataset(simulate(seed_truth(), seed_grid(), NoiseModel(),
                               np.random.default_rng(2)), "dashboard session")
    files = build_report_bytes(solve(data), data, {"note": "from the GUI", "mode": "simulated"})
    assert set(files) == {"report.html", "report.pdf", "calibration.json", "residuals.csv"}
    assert files["report.pdf"].startswith(b"%PDF") and files["report.html"].startswith(
        b"<!DOCTYPE html>")
    assert b"from the GUI" in files["report.html"]
    assert json.loads(files["calibration.json"])["report"]["meta"]["note"] == "from the GUI"


# ---- browser and PDF -------------------------------------------------------------------------

def test_html_opens_in_chromium_without_requests_or_errors(session_report: dict,
                                                           tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    html = session_report["out"] / "report.html"
    requests: list[str] = []
    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking"])
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 1400})
            page.on("request", lambda r: requests.append(r.url))
            page.on("console", lambda m: problems.append(f"{m.type}: {m.text}")
                    if m.type in ("error", "warning") else None)
            page.on("pageerror", lambda e: problems.append(str(e)))
            page.goto(html.as_uri())
            page.wait_for_load_state("load")
            loaded = page.evaluate("Array.from(document.images).map(i => i.naturalWidth)")
            status = page.get_attribute("#verdict", "data-status")
            page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
        finally:
            browser.close()
    assert problems == []
    assert [u for u in requests if not u.startswith("data:")] == [html.as_uri()]
    assert len(loaded) == 5 and min(loaded) > 300
    assert status in ("consistent", "review")
    assert (tmp_path / "report.png").stat().st_size > 50_000


def test_pdf_pages(session_report: dict, tmp_path: Path) -> None:
    from PIL import Image

    from app.report.plots import FIGURES

    pdf = session_report["out"] / "report.pdf"
    subprocess.run(["pdftoppm", "-png", "-r", "50", str(pdf), str(tmp_path / "page")],
                   check=True, timeout=120)
    pages = sorted(tmp_path.glob("page-*.png"))
    text = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True,
                          text=True, check=True, timeout=120).stdout.split("\f")
    n = len(pages)
    assert 5 <= n <= 9
    for k in range(n):
        assert f"page {k + 1} / {n}" in text[k]
    joined = "".join(text)
    for heading in ("Laser beam calibration report", "Verdict", "Result",
                    "Residuals (seed Table 1 style, mm)", "Outliers", "Warnings",
                    "Platform calibration", "Review and approval",
                    *(caption for _, caption, _ in FIGURES)):
        assert heading in joined, heading
    solved = session_report["solved"]
    assert f"{solved.point('x_t'):.4f}"[:6] in joined
    for page in pages:
        gray = np.asarray(Image.open(page).convert("L"), dtype=float)
        assert gray.shape[0] > gray.shape[1]  # A4 portrait
        assert np.mean(gray < 200) > 0.004, f"{page.name} is blank"


# ---- operator errors -------------------------------------------------------------------------

@pytest.mark.parametrize("args, message", [
    (["missing.csv", "--out", "r.html"], "no such file"),
    (["DATA", "--out", "nodir/r.html"], "does not exist"),
    (["DATA", "--calib", "bad.json", "--out", "r.html"], "not valid JSON"),
    (["DATA", "--measure", "list.json", "--out", "r.html"], "expected a JSON object"),
    (["DATA", "--calib", "bad.json", "--holdout", "0.3", "--out", "r.html"], "do not apply"),
    (["DATA", "--holdout", "1.5", "--out", "r.html"], "between 0 and 1"),
])
def test_errors_are_one_line_exit_2(args: list[str], message: str, tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str],
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "DATA.csv").write_bytes(EXAMPLE.read_bytes())
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    args = [a.replace("DATA", "DATA.csv") if a == "DATA" else a for a in args]
    assert main(["report", *args]) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(r"error: [^\n]+\n", err) and message in err, err

"""The served dashboard in headless Chromium: a whole calibration on the simulated cell."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import pytest

from drivers.sim.workcell import load_workcell
from tests.e2e.conftest import Served

#: Shown value within this many shown sigmas of the simulated truth.
K_SIGMA = 4.0


def sim_truth() -> dict[str, float]:
    """H of the default simulated cell (sensor not re-zeroed): T, u' and the plate tilt."""
    wc = load_workcell(None)
    t, u = wc.beam.t, wc.beam.u_prime
    return {"x_t": t[0], "y_t": t[1], "z_t_minus_delta": t[2] - wc.plate.delta, "a": u[0],
            "b": u[1], "c": u[2], "alpha": wc.plate.alpha, "beta": wc.plate.beta,
            "gain": wc.beam.gain}


def shown_parameters(page, marker: str = "z_t_minus_delta") -> dict[str, tuple[float, float]]:
    """``name -> (value, sigma)`` read from the results table holding ``marker``."""
    table = page.locator("table", has_text=marker)
    out = {}
    for text in table.locator("tbody tr").all_inner_texts():
        cells = [c.strip() for c in re.split(r"\t|\n", text) if c.strip()]
        out[cells[0]] = (float(cells[1]), float(cells[2]))
    return out


def test_calibration_in_the_browser_matches_the_simulated_truth(
        served: Served, browser, tmp_path: Path) -> None:
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.set_default_timeout(60_000)
    console: list[str] = []
    page.on("console", lambda m: console.append(m.text))
    page.goto(served.url)
    assert page.url.endswith(f":{served.port}/")          # token swapped for the cookie
    page.locator("canvas").first.wait_for()                # the 3-D scene
    page.get_by_text("Connected", exact=False).first.wait_for()   # simulated cell connected

    page.get_by_role("tab", name="Acquire").click()
    page.get_by_role("button", name="Start acquisition").click()
    page.get_by_text(re.compile(r"finished: 42 / 42 poses")).wait_for(timeout=120_000)
    assert served.session.exists()

    page.get_by_role("tab", name="Solve").click()
    page.get_by_role("button", name="Solve H").click()
    page.locator("table", has_text="z_t_minus_delta").wait_for()
    shown = shown_parameters(page)
    truth = sim_truth()
    assert set(truth) <= set(shown)
    for name, expected in truth.items():
        value, sigma = shown[name]
        assert sigma > 0
        assert abs(value - expected) <= K_SIGMA * sigma, (name, value, sigma, expected)
    page.get_by_text("condition number", exact=False).first.wait_for()

    page.get_by_role("tab", name="Export").click()
    with page.expect_download() as info:
        page.get_by_role("button", name="Download solve JSON").click()
    calib = json.loads(Path(info.value.path()).read_text())
    assert calib["n_points"] == 42
    assert calib["params"]["x_t"] == pytest.approx(shown["x_t"][0], abs=1e-6)
    with page.expect_download() as info:
        page.get_by_role("button", name="Download session CSV").click()
    csv = Path(info.value.path()).read_text().splitlines()
    assert csv[0].startswith("# lasercal session") and len(csv) == 2 + 1 + 42
    with page.expect_download(timeout=120_000) as info:
        page.get_by_role("button", name="Download report").click()
    report = zipfile.ZipFile(Path(info.value.path()))
    assert sorted(report.namelist()) == ["calibration.json", "report.html", "report.pdf",
                                         "residuals.csv"]
    assert json.loads(report.read("calibration.json"))["params"]["x_t"] == pytest.approx(
        shown["x_t"][0], abs=1e-6)

    # Measure tab: arm motion, scan the aluminium side plate, compare with the workcell TOML
    page.get_by_role("tab", name="Jog").click()
    page.get_by_label("Arm motion").check()
    page.get_by_role("tab", name="Measure").click()
    page.get_by_role("button", name="Scan side plate").click()
    page.locator("table", has_text="plane parameter").wait_for()
    plane = shown_parameters(page, "plane parameter")
    side = load_workcell(None).side_plate
    for name, expected in (("alpha", side.alpha), ("beta", side.beta)):
        value, sigma = plane[name]
        assert sigma > 0 and abs(value - expected) <= 3 * sigma, (name, value, sigma, expected)
    shot = tmp_path / "dashboard-measure.png"
    page.screenshot(path=str(shot))
    print(f"screenshot: {shot}")

    page.get_by_role("tab", name="Solve").click()
    shot = tmp_path / "dashboard-solved.png"
    page.screenshot(path=str(shot))
    assert shot.stat().st_size > 20_000
    print(f"screenshot: {shot}")
    assert not [c for c in console if "Version mismatch" in c]
    page.close()


@pytest.mark.parametrize("path", ["/", "/index.html"])
def test_page_without_token_is_refused(served: Served, browser, path: str) -> None:
    context = browser.new_context()
    page = context.new_page()
    response = page.goto(f"http://127.0.0.1:{served.port}{path}")
    assert response is not None and response.status == 403
    context.close()

"""report.html of a replay, in real headless Chromium: the slider moves the marker."""

from __future__ import annotations

from pathlib import Path

import pytest

from client.replay import ReplayConfig, replay
from client.report import build_report, write_report
from client.transports import LocalClient
from service.maps.route_map import save_map
from tests.browser import ARTIFACTS, browser_page

LENGTH = 30


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory: pytest.TempPathFactory, small_map, sunny2) -> tuple:
    maps = tmp_path_factory.mktemp("report_maps")
    save_map(small_map, maps / "small")
    cfg = ReplayConfig("small", "dpso", {}, seed=3, start=10, length=LENGTH)
    client = LocalClient(maps)
    try:
        runs = replay(client, sunny2, cfg)
    finally:
        client.close()
    out = tmp_path_factory.mktemp("report")
    write_report(build_report(sunny2, cfg, runs, "local"), runs, small_map.positions, out)
    return out, runs[0]


def test_report_html_is_self_contained(report_dir) -> None:
    out, _ = report_dir
    page = (out / "report.html").read_text()
    assert "<script src" not in page and "<link" not in page and "http://" not in page.replace(
        "http://www.w3.org/2000/svg", "")
    assert "[report.html](report.html)" in (out / "report.md").read_text()


def test_slider_moves_the_marker(report_dir) -> None:
    out, run = report_dir
    with browser_page(1200, 900) as page:
        page.goto((Path(out) / "report.html").as_uri())
        marker = page.locator("#est-marker")
        assert marker.get_attribute("data-frame") == "0"
        assert float(marker.get_attribute("data-x")) == pytest.approx(run.estimates[0].x,
                                                                      abs=0.01)
        first = (marker.get_attribute("cx"), marker.get_attribute("cy"))
        truth_first = page.locator("#truth-marker").get_attribute("cx")
        cursor_first = page.locator("#cursor").get_attribute("x1")

        k = LENGTH - 1
        page.locator("#slider").fill(str(k))
        assert marker.get_attribute("data-frame") == str(k)
        e = run.estimates[k]
        assert float(marker.get_attribute("data-x")) == pytest.approx(e.x, abs=0.01)
        assert float(marker.get_attribute("data-y")) == pytest.approx(e.y, abs=0.01)
        assert marker.get_attribute("data-status") == e.status
        assert (marker.get_attribute("cx"), marker.get_attribute("cy")) != first
        assert page.locator("#truth-marker").get_attribute("cx") != truth_first
        assert page.locator("#cursor").get_attribute("x1") != cursor_first
        assert page.locator('dd[data-field="frame"]').inner_text().startswith(f"{k} /")
        err = float(page.locator('dd[data-field="error"]').inner_text().split()[0])
        assert err == pytest.approx(float(run.errors[k]), abs=0.01)
        # the keyboard steps back one frame
        page.locator("#slider").focus()
        page.keyboard.press("ArrowLeft")
        assert marker.get_attribute("data-frame") == str(k - 1)
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "report-html.png"))

"""The fleet viewer in real headless Chromium against a real server (HTTP + Zenoh robots)."""

from __future__ import annotations

import re
from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest

from client.transports import HttpClient, ZenohClient
from service.engine.localization_service import LocalizationService
from service.server import free_port, running_server
from service.settings import Settings
from tests.browser import ARTIFACTS, browser_page

TOKEN = "viewer-test-token"
STATUSES = ("initializing", "tracking", "recovering", "lost")
LEGEND_ITEMS = ("robot", "accuracy", "path", "hypotheses", "particles", "map-images")
STATUS_COLORS = {"tracking": "#2e9d4f", "lost": "#d62728"}

# the canvas pixel under a robot's marker, as #rrggbb (the marker's centre is its fill)
PIXEL_JS = """(id) => {
  const li = document.querySelector(`li.robot[data-robot="${id}"]`);
  if (!li || li.dataset.sx === undefined) return null;
  const c = document.getElementById('scene'), dpr = window.devicePixelRatio || 1;
  const d = c.getContext('2d').getImageData(Math.round(li.dataset.sx * dpr),
                                            Math.round(li.dataset.sy * dpr), 1, 1).data;
  return '#' + [d[0], d[1], d[2]].map((v) => v.toString(16).padStart(2, '0')).join('');
}"""


@pytest.fixture(scope="module")
def viewer_server(tmp_path_factory: pytest.TempPathFactory, small_map) -> Iterator[dict]:
    from service.maps.route_map import save_map

    maps = tmp_path_factory.mktemp("viewer_maps")
    save_map(small_map, maps / "small")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(), auth_token=TOKEN,
                        zenoh_listen=[endpoint], zenoh_multicast_scouting=False, workers=2,
                        zenoh_unauthenticated=True)  # loopback only, accepted here
    with running_server(LocalizationService(settings)) as url:
        yield {"url": url, "zenoh": endpoint}


def test_viewer_needs_the_token(viewer_server) -> None:
    url = viewer_server["url"]
    r = httpx.get(f"{url}/viewer")
    assert r.status_code == 401 and "?token=" in r.json()["error"]
    assert httpx.get(f"{url}/viewer", params={"token": "wrong"}).status_code == 401
    r = httpx.get(f"{url}/viewer", params={"token": TOKEN})
    assert r.status_code == 200 and "viewer/static/js/main.js" in r.text
    js = httpx.get(f"{url}/viewer/static/js/main.js")  # code only, open like /docs
    assert js.status_code == 200 and "javascript" in js.headers["content-type"]
    # the icon: linked by the page (no /favicon.ico 404 on load) and at /favicon.ico, open
    icon = re.search(r'<link rel="icon" [^>]*href="([^"]+)"', r.text)
    assert icon is not None
    for path in (icon.group(1), "favicon.ico"):
        got = httpx.get(f"{url}/{path}")
        assert got.status_code == 200 and got.headers["content-type"] == "image/svg+xml"
        assert got.text.startswith("<svg")
    # the API itself still takes the token only as a header
    assert httpx.get(f"{url}/maps", params={"token": TOKEN}).status_code == 401


def test_the_panel_shows_what_a_learning_robot_taught(viewer_server, sunny2) -> None:
    """The selected robot's entry shows, where it learns, its frames taught of those judged
    (its GET /sessions/{id}'s ``learning``); another robot shows none. Two frames: both
    stopped by the path gate, so the shared map learns nothing."""
    url = viewer_server["url"]
    api = HttpClient(url, token=TOKEN)
    try:
        api.create_session("robot-learn", "small", learn=True, condition="sunny")
        api.create_session("robot-plain", "small")
        for i in range(2):
            for robot in ("robot-learn", "robot-plain"):
                api.localize(robot, sunny2.image_path(5 + i).read_bytes(), t=0.5 * i)
        with browser_page() as page:
            page.goto(f"{url}/viewer?token={TOKEN}")
            page.wait_for_selector('#conn[data-state="live"]')
            learner = page.locator('li.robot[data-robot="robot-learn"]')
            plain = page.locator('li.robot[data-robot="robot-plain"]')
            page.wait_for_selector('li.robot[data-robot="robot-learn"]')
            assert learner.locator(".taught").inner_text() == "–"  # not selected yet
            learner.locator(".name").click()  # selected: its session is read
            page.wait_for_selector('li.robot[data-robot="robot-learn"][data-taught="0"]')
            assert learner.locator(".taught").inner_text() == "0 of 2"
            plain.locator(".name").click()  # another robot selected: it does not learn
            page.wait_for_selector('li.robot[data-robot="robot-learn"][data-taught=""]')
            assert plain.get_attribute("data-taught") == ""
            assert plain.locator(".taught").inner_text() == "–"
    finally:
        for robot in ("robot-learn", "robot-plain"):
            api.delete_session(robot)
        api.close()


def test_two_robots_live_and_one_gets_lost(viewer_server, sunny2) -> None:
    url = viewer_server["url"]
    api = HttpClient(url, token=TOKEN)
    z = ZenohClient([viewer_server["zenoh"]], mode="peer")
    black = cv2.imencode(".png", np.zeros((240, 320), np.uint8))[1].tobytes()
    try:
        api.create_session("robot-http", "small", "dpso", seed=1)
        z.create_session("robot-zenoh", "small", "pf-l", seed=2)  # PF-l reports `lost`
        with browser_page() as page:
            not_found: list[str] = []
            page.on("response", lambda r: not_found.append(r.url) if r.status >= 400 else None)
            page.goto(f"{url}/viewer?token={TOKEN}")
            page.wait_for_selector('#conn[data-state="live"]')
            assert page.locator("#map-select").input_value() == "small"
            # a legend for every status and everything drawn; a favicon: no 404 on load
            for key in [f'[data-status="{s}"]' for s in STATUS_COLORS] + \
                    [f'[data-item="{i}"]' for i in LEGEND_ITEMS]:
                assert page.locator(f"#legend {key}").is_visible(), key
            assert page.locator('link[rel="icon"]').count() == 1
            assert not_found == []
            for i in range(8):  # two robots stream while the page watches
                api.localize("robot-http", sunny2.image_path(5 + i).read_bytes(), t=0.5 * i)
                z.localize("robot-zenoh", sunny2.image_path(60 + i).read_bytes(), t=0.5 * i)
            for robot in ("robot-http", "robot-zenoh"):
                page.wait_for_selector(f'li.robot[data-robot="{robot}"][data-status="tracking"]')
                page.wait_for_function(f"() => ({PIXEL_JS})('{robot}') === "
                                       f"'{STATUS_COLORS['tracking']}'")
            li = page.locator('li.robot[data-robot="robot-zenoh"]')
            assert li.get_attribute("data-color") == STATUS_COLORS["tracking"]
            assert "m/s" in li.locator(".speed").inner_text()
            assert li.locator(".comparisons").inner_text().isdigit()
            # the layer the frame was matched with: the map's own images (no experience)
            assert li.locator(".experience").inner_text() == "map"
            assert "2 robots" in page.locator("#fleet-summary").inner_text()

            for i in range(4):  # frames that match nothing
                z.localize("robot-zenoh", black, t=4.0 + 0.5 * i)
            page.wait_for_selector('li.robot[data-robot="robot-zenoh"][data-status="lost"]')
            assert li.get_attribute("data-color") == STATUS_COLORS["lost"]
            page.wait_for_function(f"() => ({PIXEL_JS})('robot-zenoh') === "
                                   f"'{STATUS_COLORS['lost']}'")
            other = page.locator('li.robot[data-robot="robot-http"]')
            assert other.get_attribute("data-status") == "tracking"
            assert page.evaluate(PIXEL_JS, "robot-http") == STATUS_COLORS["tracking"]

            # particles on demand: the checkbox reconnects the stream and they are drawn (a
            # frame sent while the new stream is still connecting is not on it: frames go on
            # until one is)
            from playwright.sync_api import TimeoutError as PlaywrightTimeout

            li.locator("input[type=checkbox]").check()
            for k in range(20):
                z.localize("robot-zenoh", black, t=6.5 + 0.5 * k)
                try:
                    page.wait_for_function("() => window.swarmloc.fleet.robots"
                                           ".get('robot-zenoh')?.particles?.length > 0",
                                           timeout=2000)
                    break
                except PlaywrightTimeout:
                    continue
            else:
                pytest.fail("no particles drawn after 20 frames with the robot watched")
            assert not_found == []
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "viewer-two-robots.png"))
        assert (ARTIFACTS / "viewer-two-robots.png").stat().st_size > 10_000
    finally:
        api.close()
        z.close()

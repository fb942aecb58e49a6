"""The review page in a real headless browser (Debian's chromium, driven by selenium through
chromedriver): it loads with no console error and no request leaving the machine, shows the
right number of changes where the map says they are, opens a change on a click and on the
keyboard, and a decision made in the live page lands in the index.

`.ci/browser-deps` installs chromium and chromium-driver on a fresh machine; where they are
missing outside CI these tests are skipped (in CI, CI=true, they fail instead).
Screenshots go to the test's tmp folder; with STREETCD_SCREENSHOTS=DIR also to DIR.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from threading import Thread

import pytest

from streetcd.report.changes import load_changes
from streetcd.report.site import write_report

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    # without these two, chromium keeps trying to reach Google's servers
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--window-size=1400,900",
)
READY_S = 2.0  # issue 18: the page interactive in at most 2 s

if not (CHROMIUM and CHROMEDRIVER):
    if os.environ.get("CI"):
        pytest.fail("chromium / chromedriver missing: .ci/browser-deps installs them")
    pytest.skip(
        "chromium and chromedriver not installed (.ci/browser-deps)", allow_module_level=True
    )

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def night(tmp_path_factory):
    from test_report import make_night

    return make_night(tmp_path_factory.mktemp("night"), n_views=9)


def load(driver, url: str) -> None:
    driver.get_log("browser")  # drop what earlier pages logged
    driver.get_log("performance")
    driver.get(url)
    WebDriverWait(driver, 10).until(
        lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-ready") == "1"
    )


def console_errors(driver) -> list[str]:
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def requested_urls(driver) -> list[str]:
    """Every URL the page asked the network stack for, from the DevTools performance log."""
    urls = []
    for entry in driver.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        if msg["method"] == "Network.requestWillBeSent":
            urls.append(msg["params"]["request"]["url"])
    return urls


def ready_ms(driver) -> float:
    """Milliseconds from navigation start to the page's own "ready" mark (its list, map and
    filters drawn, keys bound), Navigation Timing / User Timing in the browser."""
    return driver.execute_script(
        "const m = performance.getEntriesByName('streetcd-ready')[0];return m ? m.startTime : null;"
    )


def screenshot(driver, path: Path, name: str) -> None:
    driver.save_screenshot(str(path / name))
    extra = os.environ.get("STREETCD_SCREENSHOTS")
    if extra:
        Path(extra).mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(Path(extra) / name))


def test_the_report_loads_offline_with_every_change(browser, night, tmp_path):
    site = tmp_path / "site"
    write_report(night.index, site)
    load(browser, (site / "index.html").as_uri())
    ms = ready_ms(browser)
    nav = browser.execute_script(
        "const n = performance.getEntriesByType('navigation')[0];"
        "return [n.domInteractive, n.domContentLoadedEventEnd, n.loadEventEnd];"
    )
    print(f"report page ready in {ms:.0f} ms (navigation: interactive, DOM loaded, load {nav} ms)")
    assert ms is not None and ms <= READY_S * 1000
    assert console_errors(browser) == []
    urls = requested_urls(browser)
    assert urls and all(u.startswith(("file://", "data:")) for u in urls), urls
    changes = load_changes(night.index)
    items = browser.find_elements(By.CSS_SELECTOR, "#list li")
    assert len(items) == len(changes) == len(night.changes)
    assert [i.get_attribute("data-id") for i in items] == [c["id"] for c in changes]
    assert browser.find_element(By.CSS_SELECTOR, '[data-n="failed"] b').text == "1"
    screenshot(browser, tmp_path, "report.png")


def test_the_map_puts_each_change_where_it_is(browser, night, tmp_path):
    """The SVG maps CRS metres to the screen: each change's circle is where its centroid
    lies in the map's frame (to a pixel), east to the right and north up."""
    site = tmp_path / "site"
    write_report(night.index, site)
    load(browser, (site / "index.html").as_uri())
    geo = browser.execute_script(
        "const svg = document.getElementById('map'), m = svg.getScreenCTM();"
        "const circles = [...svg.querySelectorAll('circle')].map(c => {"
        "  const b = c.getBoundingClientRect();"
        "  return [c.dataset.id, b.left + b.width / 2, b.top + b.height / 2]; });"
        "const line = svg.querySelector('polyline').getBoundingClientRect();"
        "return {ctm: [m.a, m.b, m.c, m.d, m.e, m.f], circles, line_top: line.top,"
        " origin: svg.dataset.origin.split(' ').map(Number)};"
    )
    # the map's user units to the screen, as the browser lays the SVG out
    a, b, c, d, e, f = geo["ctm"]
    east, north = geo["origin"]  # the map frame's north-west corner in the CRS
    by_id = {c["id"]: c for c in load_changes(night.index)}
    assert len(geo["circles"]) == len(by_id)
    for cid, sx, sy in geo["circles"]:
        x, y = by_id[cid]["centroid"][:2]
        ux, uy = x - east, north - y  # metres east and south of that corner
        assert abs(sx - (a * ux + c * uy + e)) < 0.5, cid
        assert abs(sy - (b * ux + d * uy + f)) < 0.5, cid
        assert sy < geo["line_top"]  # the façade is north of the cameras' track: above it
    xs = sorted((by_id[c]["centroid"][0], sx) for c, sx, _ in geo["circles"])
    assert [s for _, s in xs] == sorted(s for _, s in xs)  # east is to the right


def test_a_click_and_the_keys_open_a_change(browser, night, tmp_path):
    site = tmp_path / "site"
    write_report(night.index, site)
    load(browser, (site / "index.html").as_uri())
    items = browser.find_elements(By.CSS_SELECTOR, "#list li")
    items[1].click()
    detail = browser.find_element(By.ID, "detail")
    assert detail.get_attribute("data-id") == items[1].get_attribute("data-id")
    WebDriverWait(browser, 5).until(
        lambda d: d.execute_script(
            "return [...document.querySelectorAll('#detail img')]"
            ".every(i => i.complete && i.naturalWidth > 0)"
        )
    )
    assert browser.find_elements(By.CSS_SELECTOR, "#detail .swipe .box")  # where it is
    body = browser.find_element(By.TAG_NAME, "body")
    body.send_keys("j")
    body.send_keys("\n")
    assert detail.get_attribute("data-id") == items[2].get_attribute("data-id")
    body.send_keys("k", "k", "\n")
    assert detail.get_attribute("data-id") == items[0].get_attribute("data-id")
    body.send_keys("b")
    assert "blink" in browser.find_element(By.CSS_SELECTOR, "#detail .swipe").get_attribute("class")
    assert console_errors(browser) == []
    screenshot(browser, tmp_path, "report-open.png")


def test_a_decision_in_the_live_page_lands_in_the_index(browser, night, tmp_path):
    from streetcd.report.server import close_server, make_server

    server = make_server(night.index, port=0, site_dir=tmp_path / "site", reviewer="tester")
    Thread(target=server.serve_forever, daemon=True).start()
    try:
        load(browser, server.url)
        assert console_errors(browser) == []
        host, port = server.server_address[:2]
        urls = requested_urls(browser)
        assert urls and all(u.startswith((f"http://{host}:{port}/", "data:")) for u in urls), urls
        first = browser.find_element(By.CSS_SELECTOR, "#list li")
        change_id = first.get_attribute("data-id")
        first.click()
        browser.find_element(By.ID, "review-note").send_keys("a poster, not a sign")
        browser.find_element(By.CSS_SELECTOR, '#detail button[data-status="false_alarm"]').click()
        WebDriverWait(browser, 5).until(  # read in the page: the detail is redrawn meanwhile
            lambda d: (
                "false alarm"
                in d.execute_script(
                    "const e = document.getElementById('review-status'); return e ? e.textContent : ''"
                )
            )
        )
        review = {c["id"]: c for c in load_changes(night.index)}[change_id]["review"]
        assert review["status"] == "false_alarm" and review["who"] == "tester"
        assert review["note"] == "a poster, not a sign"
        # the keyboard decides too, and a reload shows the index's state
        browser.find_element(By.TAG_NAME, "body").send_keys("c")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            review = {c["id"]: c for c in load_changes(night.index)}[change_id]["review"]
            if review["status"] == "confirmed":
                break
            time.sleep(0.1)
        assert review["status"] == "confirmed"
        load(browser, server.url)
        first = browser.find_element(By.CSS_SELECTOR, f'#list li[data-id="{change_id}"]')
        assert "confirmed" in first.text
        assert console_errors(browser) == []
        screenshot(browser, tmp_path, "serve.png")
    finally:
        server.shutdown()
        close_server(server)

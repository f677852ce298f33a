"""`refflow gui` in a real headless browser (Debian's chromium + chromium-driver, Selenium).

The issue's scenario on the Tacoma clip: open the page, draw the ROI and a polygon on the deck,
click a scale, run `dis`, wait for the plots, download the CSV, and check that it equals what
`refflow track` writes for the same project in the shell. A bad value typed on the page shows
the CLI's own one-line message. Skips, saying why, where no browser can be had (`make test`
installs one as root with apt-get).

REFFLOW_GUI_SCREENSHOT=docs/gui.png keeps the page's screenshot after the run (the README's); it
measures the whole clip then (248 frames, where the deck's twisting shows in the spectrum) rather
than the first 60.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from flow.gui import project as projects

ROOT = Path(__file__).resolve().parents[2]
CLIP = ROOT / ".." / "shared" / "data" / "tacoma_bridge.mp4"
# The deck's surface and curb in frame 0 (as tests/integration/test_cli_tacoma.py measures it).
DECK = [(0, 160), (140, 125), (190, 120), (190, 215), (0, 215)]
ROI = (0, 110, 200, 110)
# Two points across the near lane, taken as 3.8 m apart (illustrative: no survey of the clip).
SCALE_POINTS = [(40, 236), (232, 236)]
LANE_MM = "3800"
FRAMES = 248 if os.environ.get("REFFLOW_GUI_SCREENSHOT") else 60

needs_clip = pytest.mark.skipif(not CLIP.is_file(), reason=f"shared test data absent: {CLIP}")


def chromium() -> str | None:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)


@pytest.fixture
def browser(tmp_path):
    """Headless Chromium driven by the system's chromedriver (Selenium never downloads one)."""
    try:
        from selenium import webdriver
        from selenium.common.exceptions import WebDriverException
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed: pip install -e '.[test]'")
    driver_path, browser_path = shutil.which("chromedriver"), chromium()
    if driver_path is None or browser_path is None:
        pytest.skip("no chromium/chromedriver on PATH: install Debian's chromium and chromium-driver "
                    "(`make test` does as root: apt-get install chromium chromium-driver)")
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    options = webdriver.ChromeOptions()
    options.binary_location = browser_path
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1480,1400",
                     "--force-device-scale-factor=1", "--disable-gpu", "--hide-scrollbars"):
        options.add_argument(argument)
    options.add_experimental_option("prefs", {"download.default_directory": str(downloads),
                                              "download.prompt_for_download": False})
    try:
        driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=options)
    except WebDriverException as err:
        pytest.skip(f"chromium does not start here: {str(err.msg or err).splitlines()[0]}")
    driver.downloads = downloads
    yield driver
    driver.quit()


@pytest.fixture
def server(tmp_path):
    from flow.gui.server import make_server

    httpd = make_server(CLIP, tmp_path / "tacoma_bridge_refflow", port=0)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    yield httpd
    httpd.shutdown()
    httpd.server_close()
    httpd.app.close()


def wait_for(driver, script: str, timeout: float = 30.0):
    """Poll the page until ``script`` returns something true; fail with the page's message."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    message = driver.execute_script("return document.getElementById('message').textContent")
    raise AssertionError(f"timed out waiting for {script!r}; the page says: {message!r}")


class Page:
    def __init__(self, driver) -> None:
        from selenium.webdriver.common.by import By

        self.driver, self.by = driver, By
        self.canvas = driver.find_element(By.ID, "frame-canvas")

    def el(self, element_id: str):
        return self.driver.find_element(self.by.ID, element_id)

    def offset(self, x: float, y: float, *, edge: bool = False) -> tuple[int, int]:
        """Selenium's offset from the canvas's centre of raw pixel (x, y) (or pixel edge)."""
        if edge:
            x, y = x - 0.5, y - 0.5
        cx, cy = self.driver.execute_script("return window.refflowApp.pixelToClient(arguments[0], arguments[1])", x, y)
        size = self.canvas.size
        return round(cx - size["width"] / 2), round(cy - size["height"] / 2)

    def actions(self):
        from selenium.webdriver.common.action_chains import ActionChains

        return ActionChains(self.driver, duration=0)

    def tool(self, name: str) -> None:
        self.driver.find_element(self.by.CSS_SELECTOR, f".tool[data-tool={name}]").click()

    def click(self, x: float, y: float) -> None:
        self.actions().move_to_element_with_offset(self.canvas, *self.offset(x, y)).click().perform()
        time.sleep(0.3)  # two clicks at once would be a double-click

    def drag(self, start: tuple[float, float], end: tuple[float, float]) -> None:
        (ax, ay), (bx, by) = self.offset(*start, edge=True), self.offset(*end, edge=True)
        (self.actions().move_to_element_with_offset(self.canvas, ax, ay).click_and_hold()
         .move_to_element_with_offset(self.canvas, bx, by).release().perform())

    def type(self, element_id: str, text: str) -> None:
        self.type_into(self.el(element_id), text)

    @staticmethod
    def type_into(field, text: str) -> None:
        field.clear()
        field.send_keys(text)

    def message(self) -> str:
        return self.driver.execute_script(
            "const m = document.getElementById('message'); return m.hidden ? '' : m.textContent")


def cli(argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flow.cli", *argv], capture_output=True, text=True, timeout=300,
                          cwd=ROOT)


@needs_clip
def test_draw_scale_run_plot_download(browser, server, tmp_path) -> None:
    out = server.app.folder.root
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    browser.get(url)
    wait_for(browser, "return document.body.dataset.ready === '1' && "
                      "document.getElementById('frame-canvas').dataset.frame === '0'")
    page = Page(browser)

    # 1. The ROI (a drag) and the deck (a polygon, closed on its first corner).
    page.tool("roi")
    page.drag(ROI[:2], (ROI[0] + ROI[2], ROI[1] + ROI[3]))
    assert page.el("roi").get_attribute("value") == ",".join(map(str, ROI))
    page.tool("mask")
    for x, y in [*DECK, DECK[0]]:
        page.click(x, y)
    regions = browser.execute_script("return window.refflowApp.regions")
    assert len(regions) == 1 and len(regions[0]["polygon"]) == len(DECK), regions
    for (x, y), (u, v) in zip(DECK, regions[0]["polygon"], strict=True):
        assert abs(x - u) <= 0.5 and abs(y - v) <= 0.5, regions
    page.type_into(page.driver.find_element(page.by.CSS_SELECTOR, "#regions li input"), "deck")

    # 2. The scale: a known length between two clicked points (the tool's own arithmetic).
    page.tool("scale")
    for x, y in SCALE_POINTS:
        page.click(x, y)
    page.type("known-length", LANE_MM)
    shown = wait_for(browser, "const t = document.getElementById('scale-result').textContent; "
                              "return t.includes('mm per pixel') && t")
    points = browser.execute_script("return window.refflowApp.scalePoints")
    distance = ((points[1][0] - points[0][0]) ** 2 + (points[1][1] - points[0][1]) ** 2) ** 0.5
    assert f"{float(LANE_MM) / distance:.5g}" in shown, shown

    # 3. The method; first a bad option, which gets the CLI's one-line message on the page.
    from selenium.webdriver.support.ui import Select

    Select(page.el("method")).select_by_value("dis")
    page.type("max-frames", "0")
    page.el("run").click()
    wait_for(browser, "return document.getElementById('run-status').dataset.state === 'failed'")
    project_file = out / "tacoma_bridge_project.json"
    expected = cli(projects.track_argv(project_file)).stderr.strip().splitlines()[-1]
    assert expected.startswith("refflow track: error: --max-frames 0")
    assert page.message() == expected
    assert not (out / "tacoma_bridge.csv").exists()

    # 4. The run: progress, then the time history and the spectrum.
    page.type("max-frames", str(FRAMES) if FRAMES < 248 else "")
    page.el("run").click()
    wait_for(browser, "return document.getElementById('results').dataset.ready === '1'", timeout=180)
    assert page.message() == ""
    result = browser.execute_script("return window.refflowApp.result")
    assert result["units"] == "mm" and result["frames"] == FRAMES and result["valid"] > FRAMES * 0.9
    assert result["spectra"]["dy"]["peak_hz"] is not None
    argv = projects.track_argv(project_file)
    assert page.el("command").text.splitlines()[0] == projects.command_line(argv)
    time.sleep(0.5)  # the smooth scroll to the plots
    for _ in range(2):  # the whole page in the screenshot (the viewer grows with the window)
        chrome = browser.execute_script("return window.outerHeight - window.innerHeight")
        page_height = browser.execute_script("return document.documentElement.scrollHeight")
        browser.set_window_size(1480, page_height + chrome)
    browser.execute_script("window.scrollTo(0, 0)")
    time.sleep(0.3)
    browser.save_screenshot(str(tmp_path / "gui.png"))
    if os.environ.get("REFFLOW_GUI_SCREENSHOT"):
        from PIL import Image

        with Image.open(tmp_path / "gui.png") as shot:  # 256 colours: a third of the bytes
            shot.convert("RGB").quantize(256, dither=Image.Dither.NONE).save(
                os.environ["REFFLOW_GUI_SCREENSHOT"], optimize=True)

    # 5. The POIs next to the corners KLT would use (`refflow pois`), on the page.
    page.el("show-pois").click()
    wait_for(browser, "const i = document.getElementById('pois-image'); return i.complete && i.naturalWidth > 0")
    assert page.el("pois-message").text.startswith("POIs: ")

    # 6. The CSV through the browser's download equals the shell's run of the same project.
    browser.find_element(page.by.CSS_SELECTOR, "a.download[data-file='tacoma_bridge.csv']").click()
    downloaded = browser.downloads / "tacoma_bridge.csv"
    end = time.monotonic() + 30
    while not downloaded.is_file() and time.monotonic() < end:
        time.sleep(0.1)
    assert downloaded.is_file(), list(browser.downloads.iterdir())
    shell_csv = tmp_path / "shell.csv"
    done = cli([*argv, "--out", str(shell_csv), "--no-progress"])
    assert done.returncode == 0, done.stderr
    assert downloaded.read_text() == shell_csv.read_text()
    assert downloaded.read_text() == (out / "tacoma_bridge.csv").read_text()

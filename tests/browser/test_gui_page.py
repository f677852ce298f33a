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

import json
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
    shown_argv = json.loads(page.el("command").get_attribute("data-argv"))
    expected = cli(shown_argv).stderr.strip().splitlines()[-1]
    assert expected.startswith("refflow track: error: --max-frames 0")
    assert page.message() == expected
    assert sorted(p.name for p in out.iterdir()) == []  # a failed run saves nothing, not even its project

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

    # 5. The CSV through the browser's download equals the shell's run of the same project.
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

    # 6. The POIs next to the corners KLT would use (`refflow pois`), on the page: a new attempt,
    # so the run's plots and downloads give way to it.
    page.el("show-pois").click()
    wait_for(browser, "const i = document.getElementById('pois-image'); return i.complete && i.naturalWidth > 0")
    assert page.el("pois-message").text.startswith("POIs: ")
    assert page.el("results").get_attribute("hidden") is not None


# -- issue 32, case 10: one attempt at a time, its project saved only when it succeeds; the scale
# says when a run is in pixels; the snap on a thin frame; peak labels; the command's wrapping ----


def write_clip(path: Path, width: int = 96, height: int = 64, frames: int = 24) -> Path:
    """A small MJPG clip: a textured band moving right by 0.5 px a frame."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (height, width + 40)), (0, 0), 1.5)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (width, height), True)
    for i in range(frames):
        shift = np.float32([[1, 0, 0.5 * (i % 40) - 20], [0, 1, 0]])
        grey = np.clip(cv2.warpAffine(texture, shift, (width, height)), 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


@pytest.fixture
def serve(tmp_path):
    """A server for a given video (its output folder tmp_path/out), and the page opened on it."""
    from flow.gui.server import make_server

    started = []

    def start(video: Path, driver):
        httpd = make_server(video, tmp_path / "out", port=0)
        threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True).start()
        started.append(httpd)
        driver.get(f"http://127.0.0.1:{httpd.server_address[1]}/")
        wait_for(driver, "return document.body.dataset.ready === '1' && "
                         "document.getElementById('frame-canvas').dataset.frame === '0'")
        return httpd, Page(driver)

    yield start
    for httpd in started:
        httpd.shutdown()
        httpd.server_close()
        httpd.app.close()


SHOWN = """const id = (i) => document.getElementById(i);
const m = id('message');
return {attempts: ['run-status', 'message', 'command'].map((i) => id(i).dataset.attempt),
        state: id('run-status').dataset.state, status: id('run-status').textContent,
        message: m.hidden ? '' : m.textContent, command: id('command').textContent,
        results_hidden: id('results').hidden, downloads: id('downloads').children.length,
        pois_hidden: id('pois-panel').hidden, units_note: !id('units-note').hidden,
        scale_note: id('scale-result').textContent}"""


def shown(driver) -> dict:
    """What the page shows of its attempt; its three parts must name the same attempt."""
    state = driver.execute_script(SHOWN)
    assert len(set(state["attempts"])) == 1, state
    return state


def test_one_attempt_at_a_time_and_its_project_only_when_it_succeeds(browser, serve, tmp_path) -> None:
    from selenium.webdriver.support.ui import Select

    httpd, page = serve(write_clip(tmp_path / "clip.avi", frames=600), browser)
    out = httpd.app.folder.root
    page.tool("mask")
    for x, y in [(10, 20), (80, 20), (80, 44), (10, 44), (10, 20)]:
        page.click(x, y)
    Select(page.el("method")).select_by_value("dis")
    page.type("max-frames", "10")
    # No scale: the scale section says a run now measures in pixels, and so do the results.
    assert page.el("scale-result").text == "no scale yet: a run now measures in pixels"
    page.el("run").click()
    wait_for(browser, "return document.getElementById('results').dataset.ready === '1'", timeout=120)
    first = shown(browser)
    assert first["state"] == "done" and "in pixels: no scale was given" in first["status"], first
    assert first["units_note"] and first["downloads"] == 4 and first["message"] == ""
    saved = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(saved) == ["clip.csv", "clip.json", "clip_mask.png", "clip_project.json"]

    # A new run clears the plots and downloads at once; after Cancel they stay cleared, and the
    # saved project is the succeeded run's.
    page.type("max-frames", "")
    page.el("run").click()
    started = shown(browser)
    assert started["results_hidden"] and started["downloads"] == 0, started
    wait_for(browser, "return !document.getElementById('cancel').disabled")
    page.el("cancel").click()
    wait_for(browser, "return document.getElementById('run-status').dataset.state === 'cancelled'", timeout=60)
    cancelled = shown(browser)
    assert cancelled["results_hidden"] and cancelled["downloads"] == 0, cancelled
    assert cancelled["message"].startswith("cancelled") and cancelled["attempts"][0] != first["attempts"][0]
    assert "--max-frames" not in cancelled["command"]  # the cancelled attempt's own command
    assert {p.name: p.read_bytes() for p in out.iterdir()} == saved

    # mm per pixel chosen and left empty: refused, said where it is typed and in the message box.
    page.el("mm-per-px").click()
    assert page.el("scale-result").text == "type the mm per pixel, or choose none (pixels only)"
    page.el("run").click()
    wait_for(browser, "return document.getElementById('run-status').dataset.state === 'failed'")
    refused = shown(browser)
    assert refused["message"].startswith("mm per pixel is empty: type the scale, or choose 'none (pixels only)'")
    assert "was refused before a command was made" in refused["command"]
    assert int(refused["attempts"][0]) > int(cancelled["attempts"][0])
    browser.find_element(page.by.CSS_SELECTOR, "input[name=scale-mode][value=none]").click()

    # No polygon: the page's words, not the tool's "pass exactly one of --mask...".
    browser.find_element(page.by.CSS_SELECTOR, "#regions li button").click()
    page.el("run").click()
    wait_for(browser, "return document.getElementById('message').textContent.startsWith('no POI region')")
    assert shown(browser)["message"].startswith("no POI region: draw a polygon around the member first")

    # A failed save after a failed run: status, message and command all of the save.
    page.type("max-frames", "1.5")
    page.el("save").click()
    wait_for(browser, "return document.getElementById('message').textContent.includes('--max-frames')")
    failed_save = shown(browser)
    assert failed_save["status"].startswith(f"save #{failed_save['attempts'][0]}: failed"), failed_save
    assert {p.name: p.read_bytes() for p in out.iterdir()} == saved


def test_the_first_corner_snaps_only_where_the_frame_is_large_enough(browser, serve, tmp_path) -> None:
    from selenium.webdriver.common.keys import Keys

    httpd, page = serve(write_clip(tmp_path / "thin.avi", width=1280, height=40, frames=3), browser)
    page.tool("mask")
    # A 40-px-high frame shown about 30 px high: a corner 6 px from the first one is a corner.
    corners = [(100, 5), (600, 5), (600, 35), (106, 8)]
    for x, y in corners:
        page.click(x, y)
    assert browser.execute_script("return window.refflowApp.regions.length") == 0
    page.canvas.send_keys(Keys.ENTER)
    regions = browser.execute_script("return window.refflowApp.regions")
    assert len(regions) == 1 and len(regions[0]["polygon"]) == 4, regions
    # Fewer than three corners never close, by Enter or a click on the first corner.
    page.click(200, 10)
    page.click(300, 10)
    page.click(200, 10)
    page.canvas.send_keys(Keys.ENTER)
    assert browser.execute_script("return window.refflowApp.regions.length") == 1
    assert "at least three corners" in page.el("tool-help").text


def test_peak_labels_never_overlap(browser, serve, tmp_path) -> None:
    httpd, page = serve(write_clip(tmp_path / "clip.avi"), browser)
    boxes = browser.execute_script("""
        document.getElementById('results').hidden = false;
        const plot = window.refflowApp.plots.spectrum;
        const freqs = Array.from({length: 200}, (_, i) => i * 0.05);
        const peaks = [1.0, 1.0, 1.02, 1.05, 5.0, 9.9, 9.95];
        plot.set({title: 'amplitude spectrum', x: 'frequency (Hz)', y: 'amplitude (px)',
                  series: [{name: 'dx, peak 1.000 Hz', x: freqs, y: freqs.map(Math.sin), color: '#2563eb'},
                           {name: 'dy, peak 9.950 Hz', x: freqs, y: freqs.map(Math.cos), color: '#ea580c'}],
                  markers: peaks.map((x) => ({x, label: `${x.toFixed(3)} Hz`, color: '#2563eb'}))});
        return {labels: plot.labelBoxes, legend: plot.legendBox, pad: plot.pad, w: plot.w, h: plot.h};""")
    labels, legend = boxes["labels"], boxes["legend"]
    assert len(labels) == 7, labels

    def overlap(p, q):
        return p["x"] < q["x"] + q["w"] and q["x"] < p["x"] + p["w"] and p["y"] < q["y"] + q["h"] and q["y"] < p["y"] + p["h"]

    for i, box in enumerate(labels):
        assert not overlap(box, legend), (box, legend)
        assert boxes["pad"]["l"] <= box["x"] and box["x"] + box["w"] <= boxes["w"] - boxes["pad"]["r"], box
        for other in labels[i + 1:]:
            assert not overlap(box, other), (box, other)


def test_the_shell_command_wraps_between_arguments(browser, serve, tmp_path) -> None:
    httpd, page = serve(write_clip(tmp_path / "clip.avi"), browser)
    page.tool("mask")
    for x, y in [(10, 20), (80, 20), (80, 44), (10, 44), (10, 20)]:
        page.click(x, y)
    page.el("mm-per-px").click()
    page.type("mm-per-px", "0.25")
    page.type("params", "finest_scale=0")
    page.el("save").click()
    wait_for(browser, "return document.getElementById('run-status').dataset.state === 'saved'")
    browser.execute_script("document.getElementById('shell').style.width = '520px'")
    pieces = browser.execute_script("""
        const pre = document.getElementById('command');
        const style = getComputedStyle(pre);
        const room = pre.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight);
        const ctx = document.createElement('canvas').getContext('2d');
        ctx.font = style.font;
        return [...pre.querySelectorAll('.line')[0].querySelectorAll('.arg')].map((piece) => {
          const range = document.createRange();
          range.selectNodeContents(piece);
          const lines = new Set([...range.getClientRects()].map((r) => Math.round(r.top))).size;
          return {text: piece.textContent, lines, fits: ctx.measureText(piece.textContent).width < room - 2,
                  top: Math.round(piece.getBoundingClientRect().top)};
        });""")
    command = page.el("command").get_attribute("textContent").split("\n")[0]
    assert command == " ".join(p["text"] for p in pieces) and command.startswith("refflow track ")
    assert len({p["top"] for p in pieces}) >= 3, pieces  # it does wrap, between pieces
    assert "--mm-per-px 0.25" in [p["text"] for p in pieces] and "--param finest_scale=0" in [p["text"] for p in pieces]
    for piece in pieces:
        assert piece["lines"] == 1 or not piece["fits"], piece  # only a piece wider than the box breaks

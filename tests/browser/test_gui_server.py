"""`refflow gui` without a browser: the path checks, the project -> `refflow track` arguments,
and the server's API (what it refuses, the CLI's messages, a run, its result and a cancel)."""

from __future__ import annotations

import argparse
import contextlib
import http.client
import io
import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.gui import project as projects
from flow.gui.command import add_parser
from flow.gui.paths import OutputFolder, PathRefused
from flow.io.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
CLIP = ROOT / ".." / "shared" / "data" / "tacoma_bridge.mp4"
DECK = [[0, 160], [140, 125], [190, 120], [190, 215], [0, 215]]
W, H, N = 96, 64, 24


def write_clip(path: Path) -> Path:
    """A small MJPG clip: a textured band moving right by 0.5 px a frame."""
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 40)), (0, 0), 1.5)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H), True)
    for i in range(N):
        shift = np.float32([[1, 0, 0.5 * i - 20], [0, 1, 0]])
        grey = np.clip(cv2.warpAffine(texture, shift, (W, H)), 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


# -- the output folder ---------------------------------------------------------------------------


def test_output_folder_refuses_every_path_outside_it(tmp_path) -> None:
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret.csv").write_text("x")
    folder = OutputFolder(tmp_path / "out", [tmp_path / "video.mp4"])
    root = folder.root
    (root / "link").symlink_to(outside, target_is_directory=True)
    (root / "file_link.csv").symlink_to(outside / "secret.csv")
    assert folder.path("run.csv") == root / "run.csv"
    assert folder.path("sub/run.csv") == root / "sub" / "run.csv"
    assert folder.path(str(root / "run.csv")) == root / "run.csv"  # absolute, but inside
    refused = {"../run.csv": "climbs out with '..'", "sub/../../run.csv": "climbs out with '..'",
               "/etc/passwd": "lies outside the output folder", str(outside / "secret.csv"): "lies outside",
               "link/secret.csv": "symbolic link", "file_link.csv": "symbolic link", "": "no file name",
               ".": "outside the output folder", "a\nb.csv": "control characters"}
    for name, reason in refused.items():
        with pytest.raises(PathRefused, match=reason) as caught:
            folder.path(name)
        assert "\n" not in str(caught.value).replace(repr(name), ""), "one line"
    with pytest.raises(PathRefused, match="not a file the page offers"):
        folder.existing("run.npz", (".csv",))
    with pytest.raises(FileNotFoundError):
        folder.existing("missing.csv", (".csv",))


def test_output_folder_never_holds_or_overwrites_an_input(tmp_path) -> None:
    video = tmp_path / "out" / "clip.mp4"
    video.parent.mkdir()
    video.write_bytes(b"")
    folder = OutputFolder(tmp_path / "out", [video])
    with pytest.raises(PathRefused, match="is the run's input"):
        folder.path("clip.mp4")
    images = tmp_path / "frames"
    images.mkdir()
    with pytest.raises(InputError, match="inside the input"):
        OutputFolder(images / "out", [images])
    (tmp_path / "a_file").write_text("")
    with pytest.raises(InputError, match="is a file, not a folder"):
        OutputFolder(tmp_path / "a_file" / "out")


def test_run_names_are_plain_file_names() -> None:
    assert projects.files_of("deck")["csv"] == "deck.csv"
    assert projects.files_of("deck")["sidecar"] == "deck.json"
    for bad in ("", "../deck", "a/b", "/tmp/x", ".hidden", "deck.", None, "x" * 101):
        with pytest.raises(InputError, match="not a plain file name"):
            projects.check_name(bad)


# -- the project and its command line -------------------------------------------------------------


def page(**changes):
    state = {"roi": [0, 110, 200, 110], "regions": [{"label": "deck", "polygon": DECK}],
             "background": [{"label": "tower", "polygon": [[200, 10], [230, 10], [230, 60], [200, 60]]}],
             "scale": {"known_length_mm": "3800", "between_px": [[40, 236], [232.5, 236]]}, "method": "dis",
             "options": {"preset": "fast", "reference_frame": "0", "reference_average": "3", "grid_step": "2",
                         "max_frames": "60", "filter": "", "jobs": "", "params": "finest_scale=0\n"}}
    state.update(changes)
    return state


def save(tmp_path: Path, state: dict, name: str = "deck") -> Path:
    project = projects.from_page(state, video=tmp_path / "clip.mp4", name=name)
    path = tmp_path / f"{name}_project.json"
    path.write_text(json.dumps(project))
    return path


def test_track_argv_spells_out_the_project(tmp_path) -> None:
    path = save(tmp_path, page())
    saved = json.loads(path.read_text())
    assert saved["mask"] == "deck_mask.png" and saved["out"] == "deck.csv"  # beside the project
    assert saved["scale"] == {"known_length_mm": 3800.0, "between_px": [40.0, 236.0, 232.5, 236.0]}
    assert projects.track_argv(path) == [
        "track", str(tmp_path / "clip.mp4"), "--roi", "0,110,200,110", "--mask", str(tmp_path / "deck_mask.png"),
        "--reference-average", "3", "--grid-step", "2",
        "--background-mask", str(tmp_path / "deck_background.png"),
        "--known-length", "3800", "--between", "40,236,232.5,236", "--method", "dis",
        "--preset", "fast", "--max-frames", "60", "--param", "finest_scale=0", "--out", str(tmp_path / "deck.csv")]
    assert projects.pois_argv(path, tmp_path / "p.png")[-4:] == ["--grid-step", "2", "--out", str(tmp_path / "p.png")]
    # The CLI's own parser takes it as it is.
    from flow.cli import build_parser

    args = build_parser().parse_args(projects.track_argv(path))
    assert (args.method, args.preset, args.known_length, args.grid_step) == ("dis", "fast", 3800.0, 2)
    assert args.param == ["finest_scale=0"] and args.background_mask.endswith("deck_background.png")
    # A moved project folder: its own files move with it.
    moved = tmp_path / "moved"
    moved.mkdir()
    path.rename(moved / path.name)
    assert str(moved / "deck_mask.png") in projects.track_argv(moved / path.name)
    # mm per pixel, no ROI, no background, defaults left out
    plain = save(tmp_path, page(roi=None, background=[], scale={"mm_per_px": "0.5"}, options={}), "plain")
    assert projects.track_argv(plain) == ["track", str(tmp_path / "clip.mp4"), "--mask",
                                          str(tmp_path / "plain_mask.png"), "--mm-per-px", "0.5",
                                          "--method", "dis", "--out", str(tmp_path / "plain.csv")]
    assert projects.command_line(["track", "/a b/c.mp4"]) == "refflow track '/a b/c.mp4'"


def test_track_project_option_expands_and_is_overridden(tmp_path) -> None:
    path = save(tmp_path, page())
    argv = projects.track_argv(path)
    assert projects.expand_project_argv(["track", "--project", str(path), "--max-frames", "5"]) == [
        *argv, "--max-frames", "5"]
    assert projects.expand_project_argv(["track", f"--project={path}"]) == argv
    assert projects.expand_project_argv(["plot", "a.csv", "--out", "b.png"]) == ["plot", "a.csv", "--out", "b.png"]
    with pytest.raises(InputError, match="--project needs FILE"):
        projects.expand_project_argv(["track", "--project"])


def test_bad_projects_get_one_line_messages(tmp_path) -> None:
    with pytest.raises(InputError, match="does not exist: save one from `refflow gui`"):
        projects.track_argv(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(InputError, match="is not readable JSON"):
        projects.track_argv(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text('{"mm_per_px": 1}')
    with pytest.raises(InputError, match="is not a refflow project"):
        projects.track_argv(tmp_path / "other.json")
    path = save(tmp_path, page())
    data = json.loads(path.read_text())
    path.write_text(json.dumps({**data, "roi": "0,1,2"}))
    with pytest.raises(InputError, match=r"--roi '0,1,2' is not X,Y,W,H"):
        projects.track_argv(path)
    path.write_text(json.dumps({**data, "options": {"speed": 3}}))
    with pytest.raises(InputError, match="unknown option 'speed'"):
        projects.track_argv(path)


def argparse_message(argv: list[str]) -> str:
    """The last line argparse prints for ``argv`` (what the shell shows)."""
    from flow.cli import build_parser

    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(SystemExit):
        build_parser().parse_args(argv)
    return err.getvalue().strip().splitlines()[-1].split(": error: ", 1)[1]


def test_typed_values_get_the_cli_messages(tmp_path) -> None:
    cases = [(page(scale={"mm_per_px": "abc"}), ["--mm-per-px", "abc"]),
             (page(options={"max_frames": "1.5"}), ["--max-frames", "1.5"]),
             (page(scale={"known_length_mm": "3 m", "between_px": [[0, 0], [1, 1]]}), ["--known-length", "3 m"])]
    for state, argv in cases:
        with pytest.raises(InputError) as caught:
            projects.from_page(state, video=tmp_path / "clip.mp4", name="deck")
        assert str(caught.value) == argparse_message(["track", "v.mp4", *argv])
    with pytest.raises(InputError, match="--known-length needs --between"):
        projects.from_page(page(scale={"known_length_mm": "3"}), video=tmp_path / "clip.mp4", name="deck")


def test_the_gui_subcommand_parses() -> None:
    parser = argparse.ArgumentParser(prog="refflow")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["gui", "clip.mp4", "--port", "0", "--no-browser"])
    assert (args.input, args.port, args.no_browser, args.out_dir) == ("clip.mp4", 0, True, None)
    assert args.func.__name__ == "cmd_gui"


# -- the server ------------------------------------------------------------------------------------


@pytest.fixture
def served(tmp_path):
    from flow.gui.server import make_server

    def start(video: Path, **options):
        httpd = make_server(video, tmp_path / "out", port=0, **options)
        threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True).start()
        started.append(httpd)
        return httpd

    started: list = []
    yield start
    for httpd in started:
        httpd.shutdown()
        httpd.server_close()
        httpd.app.close()


def call(httpd, method: str, path: str, body=None, *, headers=None) -> tuple[int, str, bytes]:
    port = httpd.server_address[1]
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    data = json.dumps(body).encode() if body is not None else None
    sent = {"Host": f"127.0.0.1:{port}", **({"Content-Type": "application/json"} if data else {}), **(headers or {})}
    connection.request(method, path, body=data, headers=sent)
    reply = connection.getresponse()
    return reply.status, reply.getheader("Content-Type"), reply.read()


def error_of(reply) -> str:
    message = json.loads(reply[2])["error"]
    assert "\n" not in message
    return message


def test_server_serves_its_page_and_refuses_the_rest(served, tmp_path) -> None:
    httpd = served(write_clip(tmp_path / "clip.avi"))
    assert httpd.server_address[0] == "127.0.0.1"
    status, kind, body = call(httpd, "GET", "/")
    assert status == 200 and kind.startswith("text/html") and b"refflow" in body
    for asset in ("app.js", "plot.js", "style.css"):
        assert call(httpd, "GET", f"/static/{asset}")[0] == 200
    info = json.loads(call(httpd, "GET", "/api/info")[2])
    assert (info["width"], info["height"], info["frames"], info["name"]) == (W, H, N, "clip")
    assert "dis" in [m["name"] for m in info["methods"]]
    status, kind, body = call(httpd, "GET", "/api/frame?i=7")
    assert status == 200 and kind == "image/jpeg"
    assert cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (H, W)
    assert call(httpd, "GET", "/api/frame?i=3")[0] == 200  # backwards: the reader starts again
    assert "beyond the video's" in error_of(call(httpd, "GET", "/api/frame?i=999"))
    assert call(httpd, "GET", "/static/../server.py")[0] == 404
    assert call(httpd, "GET", "/static/%2e%2e/server.py")[0] == 404
    assert call(httpd, "GET", "/etc/passwd")[0] == 404
    for name, reason in (("../../etc/passwd", "climbs out"), ("/etc/passwd", "outside the output folder"),
                         (str(tmp_path / "clip.avi"), "outside the output folder")):
        reply = call(httpd, "GET", f"/api/file?name={name}")
        assert reply[0] == 403 and reason in error_of(reply)
    assert call(httpd, "GET", "/api/file?name=none.csv")[0] == 404
    reply = call(httpd, "GET", "/api/info", headers={"Host": "attacker.example:80"})
    assert reply[0] == 403 and "127.0.0.1" in error_of(reply)
    reply = call(httpd, "POST", "/api/project", {"name": "x"}, headers={"Origin": "http://attacker.example"})
    assert reply[0] == 403
    assert call(httpd, "POST", "/api/project", {"name": "x"}, headers={"Content-Type": "text/plain"})[0] == 415
    reply = call(httpd, "POST", "/api/project", {"name": "../x", "project": page()})
    assert reply[0] == 400 and "not a plain file name" in error_of(reply)
    assert sorted(p.name for p in httpd.app.folder.root.iterdir()) == []


def test_saved_project_mask_and_the_cli_messages(served, tmp_path) -> None:
    httpd = served(write_clip(tmp_path / "clip.avi"))
    out = httpd.app.folder.root
    band = [[10, 20], [80, 20], [80, 44], [10, 44]]
    state = page(roi=None, regions=[{"label": "band", "polygon": band}], background=[],
                 scale={"mm_per_px": "0.25"}, options={"max_frames": "10"})
    status, _, body = call(httpd, "POST", "/api/project", {"name": "band", "project": state})
    assert status == 200, body
    saved = json.loads(body)
    assert saved["command"] == projects.command_line(projects.track_argv(out / "band_project.json"))
    assert saved["project_command"] == f"refflow track --project {out / 'band_project.json'}"
    mask = cv2.imread(str(out / "band_mask.png"), cv2.IMREAD_GRAYSCALE)
    from flow.io.frames import Roi
    from flow.measure.poi import polygon_mask

    expected = polygon_mask("10,20,80,20,80,44,10,44", roi=Roi(0, 0, W, H))
    assert mask.shape == (H, W) and np.array_equal(mask > 127, expected)
    # The known length through the tool's own function (and its message for coinciding points).
    reply = call(httpd, "POST", "/api/scale", {"known_length_mm": "10", "between_px": [[0, 0], [40, 30]]})
    assert json.loads(reply[2])["mm_per_px"] == pytest.approx(10 / 50)
    reply = call(httpd, "POST", "/api/scale", {"known_length_mm": "10", "between_px": [[5, 5], [5, 5]]})
    assert reply[0] == 400 and error_of(reply) == "--between '5,5,5,5': the two points coincide; pick two distinct points"
    # No region: the page's own words (the tool would say "pass exactly one of --mask...").
    for route in ("/api/pois", "/api/run"):
        reply = call(httpd, "POST", route, {"name": "band", "project": page(regions=[], roi=None)})
        assert reply[0] == 400
        assert error_of(reply).startswith("no POI region: draw a polygon around the member first")
    reply = call(httpd, "POST", "/api/pois", {"name": "band", "project": state})
    assert reply[0] == 200 and json.loads(reply[2])["message"].startswith("POIs: ")
    assert call(httpd, "GET", "/api/file?inline=1&name=band_pois.png")[1] == "image/png"
    # An ROI off the frame: the run fails with the tool's message and leaves no output.
    bad = {**state, "roi": [50, 0, 100, 64]}
    assert call(httpd, "POST", "/api/run", {"name": "band", "project": bad})[0] == 200
    status = wait_run(httpd)
    assert status["state"] == "failed"
    assert status["message"] == (f"refflow track: error: ROI 50,0,100,64 lies outside the {W}x{H} frame: "
                                 f"pass an --roi inside 0,0,{W},{H}")
    assert not (out / "band.csv").exists()
    # A good run: its result as the page plots it, in mm.
    assert call(httpd, "POST", "/api/run", {"name": "band", "project": state})[0] == 200
    assert wait_run(httpd)["state"] == "done"
    result = json.loads(call(httpd, "GET", "/api/result?name=band")[2])
    assert result["units"] == "mm" and result["frames"] == 10 and len(result["dx"]) == 10
    assert result["dx"][-1] == pytest.approx(0.25 * 0.5 * 9, abs=0.1)  # 0.5 px a frame, 0.25 mm a px
    assert set(result["files"]) >= {"csv", "sidecar", "project", "mask"}
    status, kind, body = call(httpd, "GET", "/api/file?name=band.csv")
    assert status == 200 and kind.startswith("text/csv") and body == (out / "band.csv").read_bytes()


def wait_run(httpd, timeout: float = 120.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        status = json.loads(call(httpd, "GET", "/api/run")[2])
        if status["state"] != "running":
            return status
        time.sleep(0.05)
    raise AssertionError("the run did not end")


@pytest.mark.skipif(not CLIP.is_file(), reason=f"shared test data absent: {CLIP}")
def test_run_shows_progress_and_cancel_leaves_nothing(served) -> None:
    httpd = served(CLIP)
    out = httpd.app.folder.root
    state = page(background=[], scale={"mm_per_px": "1"}, options={"jobs": "1"})
    assert call(httpd, "POST", "/api/run", {"name": "deck", "project": state})[0] == 200
    reply = call(httpd, "POST", "/api/run", {"name": "deck", "project": state})
    assert reply[0] == 409 and "a run is in progress" in error_of(reply)
    end = time.monotonic() + 60
    while (status := json.loads(call(httpd, "GET", "/api/run")[2]))["done"] < 2 and time.monotonic() < end:
        assert status["state"] == "running", status
        time.sleep(0.05)
    assert status["total"] == 248 and "measuring: frame" in status["message"]
    assert call(httpd, "POST", "/api/cancel", {})[0] == 200
    status = wait_run(httpd)
    assert status["state"] == "cancelled" and status["returncode"] == 143, status
    assert sorted(p.name for p in out.iterdir()) == []  # not even the project: it did not run
    assert call(httpd, "POST", "/api/cancel", {})[0] == 409


def test_scale_points_are_undistorted_with_a_calibration(served, tmp_path) -> None:
    from flow.calibration import load_calibration, point_undistorter, scale_from_known_length

    calibration = tmp_path / "calib.json"
    calibration.write_text(json.dumps({"camera_matrix": [[90, 0, 48], [0, 90, 32], [0, 0, 1]],
                                       "dist_coeffs": [-0.3, 0.05, 0, 0, 0], "image_size": [W, H]}))
    httpd = served(write_clip(tmp_path / "clip.avi"), calibration=calibration)
    reply = call(httpd, "POST", "/api/scale", {"known_length_mm": "100", "between_px": [[2, 3], [90, 60]]})
    shown = json.loads(reply[2])
    expected = scale_from_known_length(100.0, "2,3,90,60", point_undistorter(load_calibration(calibration)),
                                       frame_size=(W, H))
    assert shown["undistorted"] and shown["mm_per_px"] == pytest.approx(expected, rel=1e-12)
    assert shown["mm_per_px"] != pytest.approx(100 / np.hypot(88, 57), rel=1e-3)  # the lens matters here
    reply = call(httpd, "POST", "/api/project", {"name": "cal", "project": page(roi=None, background=[])})
    argv = json.loads(reply[2])["argv"]
    assert argv[argv.index("--calibration") + 1] == str(calibration.resolve())


def test_values_starting_with_a_minus_reach_the_tool_as_values(tmp_path) -> None:
    path = save(tmp_path, page(roi=[-4, 0, 50, 50], scale={"known_length_mm": "-3", "between_px": [[-5, 2], [40, 2]]},
                               options={}))
    argv = projects.track_argv(path)
    assert "--roi=-4,0,50,50" in argv and "--between=-5,2,40,2" in argv and "--known-length=-3" in argv
    from flow.cli import build_parser

    args = build_parser().parse_args(argv)
    assert (args.roi, args.between, args.known_length) == ("-4,0,50,50", "-5,2,40,2", -3.0)


# -- issue 32, case 10: one attempt at a time; the project written only by a run that succeeded ----


def test_only_a_succeeded_run_writes_its_project_and_masks(served, tmp_path) -> None:
    httpd = served(write_clip(tmp_path / "clip.avi"))
    out = httpd.app.folder.root
    band = [[10, 20], [80, 20], [80, 44], [10, 44]]
    corner = {"label": "corner", "polygon": [[0, 0], [20, 0], [20, 12], [0, 12]]}
    state = page(roi=None, regions=[{"label": "band", "polygon": band}], background=[corner],
                 scale={"mm_per_px": "0.25"}, options={"max_frames": "10"})
    started = json.loads(call(httpd, "POST", "/api/run", {"name": "band", "project": state})[2])
    status = wait_run(httpd)
    assert status["state"] == "done", status
    # Every status of the run carries its attempt and its command (the page shows them together).
    assert status["attempt"] == started["attempt"] and status["command"] == started["command"]
    assert status["command"] == projects.command_line(projects.track_argv(out / "band_project.json"))
    assert " ".join(status["groups"]) == status["command"] and "--mm-per-px 0.25" in status["groups"]
    files = ["band.csv", "band.json", "band_background.png", "band_mask.png", "band_project.json"]
    assert sorted(p.name for p in out.iterdir()) == files  # nothing staged is left
    sidecar = json.loads((out / "band.json").read_text())
    assert sidecar["background"]["source"] == str(out / "band_background.png")  # where the mask is now
    before = {name: (out / name).read_bytes() for name in files}

    # A failed run (an ROI off the frame) with another polygon: the saved files stay as they were.
    moved = [[12, 22], [70, 22], [70, 40], [12, 40]]
    bad = {**state, "regions": [{"label": "band", "polygon": moved}], "roi": [50, 0, 100, 64]}
    reply = call(httpd, "POST", "/api/run", {"name": "band", "project": bad})
    assert reply[0] == 200 and json.loads(reply[2])["attempt"] > started["attempt"]
    status = wait_run(httpd)
    assert status["state"] == "failed" and "lies outside" in status["message"]
    assert "--roi 50,0,100,64" in status["command"]  # the failed attempt's own command
    assert {name: (out / name).read_bytes() for name in sorted(p.name for p in out.iterdir())} == before
    # The POI figure of another polygon does not save it either (only Save project does).
    reply = call(httpd, "POST", "/api/pois", {"name": "band", "project": {**bad, "roi": None}})
    assert reply[0] == 200, reply
    assert {name: (out / name).read_bytes() for name in files} == before
    assert sorted(p.name for p in out.iterdir()) == sorted([*files, "band_pois.png"])
    # A request refused outright is an attempt too, with its own number.
    reply = call(httpd, "POST", "/api/run", {"name": "band", "project": {**state, "regions": []}})
    refused = json.loads(reply[2])
    assert reply[0] == 400 and refused["state"] == "failed" and refused["attempt"] > status["attempt"]


def test_an_empty_mm_per_px_is_refused_and_a_run_without_scale_says_pixels(served, tmp_path) -> None:
    httpd = served(write_clip(tmp_path / "clip.avi"))
    band = [{"label": "band", "polygon": [[10, 20], [80, 20], [80, 44], [10, 44]]}]
    for empty in ("", " ", None):
        state = page(roi=None, regions=band, background=[], scale={"mm_per_px": empty}, options={"max_frames": "5"})
        reply = call(httpd, "POST", "/api/run", {"name": "band", "project": state})
        assert reply[0] == 400 and error_of(reply).startswith("mm per pixel is empty: type the scale, or choose "
                                                              "'none (pixels only)'")
    assert not (httpd.app.folder.root / "band.csv").exists()
    state = page(roi=None, regions=band, background=[], scale=None, options={"max_frames": "5"})
    assert call(httpd, "POST", "/api/run", {"name": "band", "project": state})[0] == 200
    status = wait_run(httpd)
    assert status["state"] == "done" and "in pixels: no scale was given" in status["message"]
    assert json.loads(call(httpd, "GET", "/api/result?name=band")[2])["units"] == "px"


def test_command_groups_keep_each_option_with_its_value(tmp_path) -> None:
    argv = projects.track_argv(save(tmp_path, page(roi=[-4, 0, 50, 50])))
    groups = projects.command_groups(argv)
    assert " ".join(groups) == projects.command_line(argv)
    assert groups[:3] == ["refflow track", str(tmp_path / "clip.mp4"), "--roi=-4,0,50,50"]
    assert "--known-length 3800" in groups and "--param finest_scale=0" in groups
    assert all(not g.startswith("--") or " " in g or "=" in g for g in groups)


def test_the_page_never_replaces_a_file_it_did_not_write(tmp_path) -> None:
    """`refflow gui clip.avi --out-dir <the video's folder>` beside the user's own clip.json and
    clip_mask.png (issue 32, case 9): the page offers another run name, and saving under the
    taken one is refused in one line; the user's files stay as they were. Its own files (a
    run whose project it wrote) it replaces as before."""
    from flow.gui.server import App

    video = write_clip(tmp_path / "clip.avi")
    mine = {tmp_path / "clip.json": b'{"my": "notes"}', tmp_path / "clip_mask.png": b"not refflow's"}
    for path, content in mine.items():
        path.write_bytes(content)
    app = App(video, tmp_path)
    try:
        assert app.info()["name"] == "clip_2"
        state = page(roi=None, regions=[{"label": "band", "polygon": [[10, 20], [80, 20], [80, 44], [10, 44]]}],
                     background=[], scale={"mm_per_px": "0.25"}, options={"max_frames": "5"})
        with pytest.raises(InputError) as refused:
            app.save({"name": "clip", "project": state})
        message = str(refused.value)
        assert "clip_mask.png, clip.json in" in message and "were not written by refflow gui" in message
        assert "choose another run name (e.g. clip_2)" in message and "\n" not in message
        assert {path: path.read_bytes() for path in mine} == mine
        assert not (tmp_path / "clip_project.json").exists()
        saved = app.save({"name": "clip_2", "project": state})
        assert (tmp_path / saved["files"]["mask"]).is_file()
        app.save({"name": "clip_2", "project": state})  # its own files: replaced
        assert app.info()["name"] == "clip_2"  # the page's own run, offered again
    finally:
        app.close()
    assert {path: path.read_bytes() for path in mine} == mine


def test_a_run_or_poi_figure_never_replaces_a_file_the_page_did_not_write(served, tmp_path) -> None:
    """Issue 32, cases 9 and 10 together: a run stages its project and masks and renames them
    into place when it succeeds; the files it would put in place (and its CSV, sidecar and POI
    figure) are checked before anything is staged, so a run or POI figure under a name whose
    files are the user's own is refused in one line, as an attempt of its own, and leaves
    nothing (no staging folder either). Under a free name it runs, and its next run replaces
    the page's own files as before."""
    out = tmp_path / "out"
    out.mkdir()
    video = write_clip(out / "clip.avi")
    mine = {out / "clip.json": b'{"my": "notes"}', out / "clip_mask.png": b"not refflow's"}
    for path, content in mine.items():
        path.write_bytes(content)
    before = sorted(p.name for p in out.iterdir())
    httpd = served(video)
    assert httpd.app.folder.root == out
    assert json.loads(call(httpd, "GET", "/api/info")[2])["name"] == "clip_2"
    state = page(roi=None, regions=[{"label": "band", "polygon": [[10, 20], [80, 20], [80, 44], [10, 44]]}],
                 background=[], scale={"mm_per_px": "0.25"}, options={"max_frames": "5"})
    attempt = 0
    for route in ("/api/run", "/api/pois", "/api/project"):
        reply = call(httpd, "POST", route, {"name": "clip", "project": state})
        message = error_of(reply)
        assert reply[0] == 400 and "were not written by refflow gui" in message, (route, message)
        assert "choose another run name (e.g. clip_2)" in message
        refused = json.loads(reply[2])
        assert refused["state"] == "failed" and refused["attempt"] > attempt
        attempt = refused["attempt"]
        assert sorted(p.name for p in out.iterdir()) == before  # nothing staged, nothing written
        assert {path: path.read_bytes() for path in mine} == mine
    assert json.loads(call(httpd, "GET", "/api/run")[2])["state"] == "idle"
    for _ in range(2):  # the second run replaces the first one's files: the page wrote them
        assert call(httpd, "POST", "/api/run", {"name": "clip_2", "project": state})[0] == 200
        status = wait_run(httpd)
        assert status["state"] == "done", status
        assert (out / "clip_2_mask.png").is_file() and (out / "clip_2_project.json").is_file()
        assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # the staging folder is gone
    assert {path: path.read_bytes() for path in mine} == mine

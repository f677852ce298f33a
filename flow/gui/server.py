"""The local server of ``refflow gui``: the page's static files and a small JSON API.

Standard library only (:class:`http.server.ThreadingHTTPServer`), bound to 127.0.0.1. The
measurement itself is ``refflow track`` run as a child process (the same validation and
messages as in the shell; cancel = SIGTERM, after which the tool leaves no file behind).

API (JSON bodies; errors are ``{"error": one line}`` with a 4xx status):

``GET /api/info``                 the video, the methods, the output folder, a saved project
``GET /api/frame?i=N``            frame N as a JPEG (grey, as measured; decoded on demand)
``POST /api/scale``               mm per pixel of a known length between two clicked points
``POST /api/project``             save the project JSON and its mask PNGs; the command lines
``POST /api/pois``                ``refflow pois`` on the project (not saved): the POIs next to KLT's corners
``POST /api/run``, ``GET /api/run``, ``POST /api/cancel``    run ``refflow track``; progress

Every save, POI figure and run is an attempt with a number (``attempt``, in its replies and
errors, and in every status of a run, with the run's command lines), so the page shows one
attempt's state at a time. A run's project JSON and masks are staged in a hidden folder and
replace the saved ones only when the run succeeds.
``GET /api/result?name=RUN``      the run's time history and amplitude spectra
``GET /api/file?name=FILE``       a file of the output folder (CSV, sidecar, project, PNG)
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np

from flow.gui import project as projects
from flow.gui.paths import OutputFolder, PathRefused
from flow.io.errors import InputError
from flow.io.frames import FrameSource
from flow.io.source import open_source

STATIC_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml", ".png": "image/png"}
FILE_TYPES = {".csv": "text/csv; charset=utf-8", ".json": "application/json", ".png": "image/png"}
MAX_BODY = 1 << 20
# tqdm's bar on the tool's stderr: " 45%|####5     | 27/60 [00:00<00:00, 49.9frame/s]"
PROGRESS = re.compile(r"(\d+)(?:/(\d+))? \[")


def static_files() -> dict[str, tuple[bytes, str]]:
    """The page's assets shipped in the package (``flow/gui/static``): name -> (bytes, type)."""
    folder = resources.files("flow.gui") / "static"
    found = {}
    for entry in folder.iterdir():
        suffix = Path(entry.name).suffix
        if entry.is_file() and suffix in STATIC_TYPES:
            found[entry.name] = (entry.read_bytes(), STATIC_TYPES[suffix])
    return found


def finite_list(values: Any) -> list[float | None]:
    """Floats for JSON: NaN and infinities become null."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, float).ravel()]


class Frames:
    """Frames of the video as JPEGs, decoded on demand with :class:`FrameSource`.

    One reader is kept open between requests, so stepping forward decodes only the frames in
    between; a step back starts it again. A few encoded frames are cached (bounded by bytes),
    never the video.
    """

    def __init__(self, source: FrameSource, *, cache_bytes: int = 64 << 20) -> None:
        self.source = source
        self.lock = threading.Lock()
        self.cache: OrderedDict[int, bytes] = OrderedDict()
        self.cache_bytes = cache_bytes
        self._reader: Any = None
        self._next = 0

    def _restart(self, start: int) -> None:
        if self._reader is not None:
            self._reader.close()
        self._reader, self._next = self.source.frames(start), start

    def _decode(self, index: int) -> np.ndarray | None:
        if self._reader is None or index < self._next:
            self._restart(index)
        try:
            for i, _, grey in self._reader:
                self._next = i + 1
                if i == index:
                    return grey
        except InputError:
            self._reader = None  # an unreadable image of a folder: the next request starts again
            raise
        self._reader = None
        return None

    def jpeg(self, index: int) -> bytes | None:
        import cv2

        from flow.io.frames import as_uint8

        with self.lock:
            if index in self.cache:
                self.cache.move_to_end(index)
                return self.cache[index]
            grey = self._decode(index)
            if grey is None:
                return None
            ok, data = cv2.imencode(".jpg", as_uint8(grey), [cv2.IMWRITE_JPEG_QUALITY, 92])
            blob = data.tobytes()
            self.cache[index] = blob
            while sum(map(len, self.cache.values())) > self.cache_bytes and len(self.cache) > 1:
                self.cache.popitem(last=False)
            return blob

    def close(self) -> None:
        with self.lock:
            if self._reader is not None:
                self._reader.close()
                self._reader = None


class Job:
    """One ``refflow track`` child process (attempt number ``attempt``), its progress and its last words.

    ``shown``: the attempt's command lines as the page shows them (every status carries them,
    so the page shows one attempt at a time). ``finish(succeeded)`` runs once the child has
    ended, before the state changes: it puts a succeeded run's project in place (an OSError
    fails the run with its reason) or discards a failed one's.
    """

    def __init__(self, argv: list[str], *, name: str, cwd: Path, attempt: int = 0,
                 shown: dict[str, Any] | None = None, finish: Callable[[bool], None] | None = None,
                 done_message: str = "done") -> None:
        self.argv, self.name, self.attempt, self.shown = argv, name, attempt, shown or {}
        self.finish, self.done_message = finish, done_message
        self.done, self.total = 0, None
        self.lines: list[str] = []
        self.state, self.message, self.returncode = "running", "starting refflow track", None
        self.cancelled = False
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen([sys.executable, "-m", "flow.cli", *argv], cwd=cwd, env=env,
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.thread = threading.Thread(target=self._follow, daemon=True)
        self.thread.start()

    def _line(self, text: str) -> None:
        text = text.strip()
        if not text:
            return
        match = PROGRESS.search(text)
        if match and ("|" in text or "frame" in text) and not text.startswith("refflow"):
            self.done = int(match.group(1))
            self.total = int(match.group(2)) if match.group(2) else None
            self.message = f"measuring: frame {self.done}" + (f" of {self.total}" if self.total else "")
            return
        self.lines = (self.lines + [text])[-40:]
        if text.startswith("refflow track: "):
            self.message = text

    def _follow(self) -> None:
        pending = b""
        stream = self.proc.stdout
        while chunk := stream.read1(4096):
            pending += chunk
            *parts, pending = re.split(rb"[\r\n]", pending)
            for part in parts:
                self._line(part.decode("utf-8", "replace"))
        self._line(pending.decode("utf-8", "replace"))
        rc = self.proc.wait()
        failure = None
        if self.finish is not None:
            try:
                self.finish(rc == 0)
            except OSError as err:
                failure = (f"the measurement is written but the project could not be: {err.strerror or err}: "
                           f"{err.filename or ''} (check the output folder)")
        self.returncode = rc
        if rc == 0 and failure:
            self.state, self.message = "failed", failure
        elif rc == 0:
            self.state, self.message = "done", self.done_message
            self.done = self.total or self.done
        elif self.cancelled and rc in (130, 143, -signal.SIGTERM, -signal.SIGINT):
            self.state, self.message = "cancelled", "cancelled: refflow track stopped, no output written"
        else:
            self.state = "failed"
            errors = [ln for ln in self.lines if ln.startswith("refflow track: error:")]
            self.message = errors[-1] if errors else (
                f"refflow track stopped with exit status {rc}: " + (self.lines[-1] if self.lines else "no message"))

    def cancel(self) -> None:
        if self.proc.poll() is None:
            self.cancelled = True
            self.proc.send_signal(signal.SIGTERM)

    def status(self) -> dict[str, Any]:
        return {**self.shown, "attempt": self.attempt, "kind": "run", "state": self.state, "done": self.done,
                "total": self.total, "message": self.message, "name": self.name, "returncode": self.returncode,
                "log": self.lines[-12:]}


class App:
    """What the server knows: the video, the output folder, the one run at a time."""

    def __init__(self, video: str | Path, out_dir: str | Path, *, fps: float | None = None,
                 calibration: str | Path | None = None) -> None:
        from flow.io.camfiles import companion_files

        self.video = Path(video)
        self.source = open_source(self.video, fps=fps, require_fps=False, allow_truncated=True)
        self.fps, self.calibration = fps, (str(Path(calibration).resolve()) if calibration else None)
        self.undistort_points = None
        if calibration:
            from flow.calibration import load_calibration, point_undistorter

            loaded = load_calibration(calibration)
            self.undistort_points = point_undistorter(loaded)
        self.folder = OutputFolder(out_dir, [self.video, *companion_files(self.video),
                                             *([calibration] if calibration else [])])
        self.frames = Frames(self.source)
        self.lock = threading.Lock()
        self.job: Job | None = None
        self.attempts = 0  # every save, POI figure and run is an attempt with its number
        self.statics = static_files()

    # -- the project ------------------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        from flow.methods import registry

        kinds, described = registry.kinds(), registry.describe()
        name = re.sub(r"[^A-Za-z0-9._-]", "_", self.video.stem)[:60].strip("._-")
        name = name if projects.NAME_PATTERN.fullmatch(name) else "run"
        name = projects.free_name(self.folder.root, name)  # never the user's own clip.json, clip_mask.png
        saved = None
        project_file = self.folder.root / projects.files_of(name)["project"]
        if project_file.is_file():
            try:
                saved = projects.load_project(project_file)
            except InputError as err:
                print(f"refflow gui: note: {err} (not loaded)", file=sys.stderr)
        try:
            from flow.pipeline import default_method  # what `track` runs without --method

            default = default_method()[0]
        except (ImportError, AttributeError):  # pragma: no cover - the CLI is part of the package
            default = "deepflow" if "deepflow" in kinds else next(iter(kinds))
        source = self.source
        return {"video": str(self.video), "video_name": self.video.name, "width": source.width,
                "height": source.height, "frames": source.header_frames,
                "fps": source.fps if math.isfinite(source.fps) else None,
                "calibration": self.calibration, "out_dir": str(self.folder.root), "name": name,
                "methods": [{"name": n, "kind": kinds[n], "summary": described[n]} for n in described],
                "default_method": default, "project": saved,
                "notes": list(source.notes)}

    def _project(self, body: dict[str, Any]) -> tuple[str, dict[str, Any], dict[str, Path]]:
        """The run's name, its project (checked) and where its files go."""
        name = projects.check_name(body.get("name"))
        # Every file the save, POI figure or run puts in place (the project and masks a run
        # stages and renames into place only when it succeeds, its CSV, sidecar and figure) is
        # checked here, before anything is written or staged: never one refflow gui did not write.
        projects.check_files_free(self.folder.root, name)
        project = projects.from_page(body.get("project"), video=self.video, name=name, fps=self.fps,
                                     calibration=self.calibration)
        targets = {role: self.folder.path(file) for role, file in projects.files_of(name).items()}
        return name, project, targets

    def _shown(self, name: str, project: dict[str, Any]) -> dict[str, Any]:
        """The command lines of the run ``name``'s ``project`` saved in the output folder, as the
        page shows them."""
        argv = projects.track_argv_of(project, self.folder.root)
        project_file = self.folder.root / projects.files_of(name)["project"]
        project_argv = ["track", "--project", str(project_file)]
        return {"argv": argv, "command": projects.command_line(argv), "groups": projects.command_groups(argv),
                "project_path": str(project_file), "project_command": projects.command_line(project_argv),
                "project_groups": projects.command_groups(project_argv)}

    def _write(self, project: dict[str, Any], targets: dict[str, Path]) -> None:
        """The project JSON and its mask PNGs at ``targets`` (masks first: a project never names
        a mask that is not there yet)."""
        from refflow.io import atomic_path

        if project["mask"]:
            write_mask(targets["mask"], project["regions"], self.source.size)
        if project["background"]:
            write_mask(targets["background"], project["background"]["regions"], self.source.size)
        with atomic_path(targets["project"]) as tmp:
            tmp.write_text(projects.dumps(project))

    def _next_attempt(self) -> int:
        with self.lock:
            self.attempts += 1
            return self.attempts

    def save(self, body: dict[str, Any]) -> dict[str, Any]:
        """Write the project JSON and its mask PNGs; return the files and command lines."""
        name, project, targets = self._project(body)
        self._write(project, targets)
        shown = self._shown(name, project)
        print(f"refflow gui: saved {targets['project']}\n  {shown['command']}\n  {shown['project_command']}",
              flush=True)
        return {**shown, "name": name, "files": projects.files_of(name), "attempt": self._next_attempt(),
                "kind": "save", "state": "saved", "message": f"saved {shown['project_path']}"}

    def _staged(self, name: str, project: dict[str, Any]) -> tuple[Path, dict[str, Path]]:
        """The project and its masks written into a fresh hidden folder inside the output folder
        (the same file system: moving them into place is a rename); returns the folder and the
        staged file of each role. The saved project is replaced only by a run that succeeded."""
        if not project["regions"]:
            raise InputError("no POI region: draw a polygon around the member first (POI mask tool: click its "
                             "corners, then the first corner again)")
        folder = Path(tempfile.mkdtemp(prefix=f".{name}.attempt-", dir=self.folder.root))
        staged = {role: folder / file for role, file in projects.files_of(name).items()}
        try:
            self._write(project, staged)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        return folder, staged

    def scale(self, body: dict[str, Any]) -> dict[str, Any]:
        """mm per pixel of ``known_length_mm`` between ``between_px`` (undistorted with the
        calibration), by the tool's own function and messages."""
        from flow.calibration import scale_from_known_length

        scale = projects._scale({"known_length_mm": body.get("known_length_mm"),
                                 "between_px": body.get("between_px")})
        if scale is None:
            raise InputError("--known-length needs --between X1,Y1,X2,Y2 (and vice versa)")
        between = ",".join(projects._text(v) for v in scale["between_px"])
        mm_per_px = scale_from_known_length(scale["known_length_mm"], between, self.undistort_points,
                                            frame_size=self.source.size)
        return {"mm_per_px": mm_per_px, "undistorted": self.undistort_points is not None}

    def pois(self, body: dict[str, Any]) -> dict[str, Any]:
        """``refflow pois`` on the page's project (staged, not saved): the figure of the POIs next
        to the corners KLT would use."""
        name, project, targets = self._project(body)
        shown = self._shown(name, project)
        folder, staged = self._staged(name, project)
        try:
            argv = projects.pois_argv(staged["project"], targets["pois"])
            done = subprocess.run([sys.executable, "-m", "flow.cli", *argv], capture_output=True, text=True,
                                  cwd=self.folder.root, timeout=600, stdin=subprocess.DEVNULL)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        if done.returncode != 0:
            lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
            errors = [ln for ln in lines if ln.startswith("refflow pois: error:")]
            raise InputError(errors[-1] if errors else (lines[-1] if lines else f"refflow pois failed ({done.returncode})"))
        return {**shown, "name": name, "files": projects.files_of(name), "image": targets["pois"].name,
                "attempt": self._next_attempt(), "kind": "pois", "state": "shown",
                "message": done.stdout.strip().splitlines()[-1]}

    # -- the run ------------------------------------------------------------------------------

    def run(self, body: dict[str, Any]) -> dict[str, Any]:
        """Start ``refflow track`` on the page's project. Its project JSON and masks are staged
        and put in place only when the run succeeds: a failed or cancelled run leaves the saved
        project, its masks and the last result as they were."""
        with self.lock:
            if self.job is not None and self.job.state == "running":
                raise Busy("a run is in progress: wait for it or cancel it first")
            name, project, targets = self._project(body)
            shown = self._shown(name, project)
            folder, staged = self._staged(name, project)
            # The run reads the staged masks and writes its CSV and sidecar where they belong
            # (`track` writes those only when it succeeds); the command shown names the masks'
            # places once the run has succeeded.
            named = {role: str(self.folder.root / file) for role, file in projects.files_of(name).items()}
            swap = {named[role]: str(staged[role]) for role in ("mask", "background")}
            argv = [swap.get(item, item) for item in shown["argv"]]
            csv = targets["csv"].name
            done_message = (f"done: {csv} in mm" if project["scale"] else
                            f"done: {csv} in pixels: no scale was given (step 2, Scale, gives mm)")
            self.attempts += 1
            try:
                self.job = Job(argv, name=name, cwd=self.folder.root, attempt=self.attempts, shown=shown,
                               done_message=done_message,
                               finish=lambda succeeded: self._settle(succeeded, folder, staged, targets, named))
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
            return self.job.status()

    def _settle(self, succeeded: bool, folder: Path, staged: dict[str, Path], targets: dict[str, Path],
                named: dict[str, str]) -> None:
        """A run has ended: a succeeded one's project and masks replace the saved ones (masks
        first, the project last); the staging folder goes either way."""
        try:
            if succeeded:
                roles = [role for role in ("mask", "background") if staged[role].is_file()]
                for role in [*roles, "project"]:
                    os.replace(staged[role], targets[role])
                retarget_sidecar(targets["sidecar"], {str(staged[role]): named[role] for role in roles})
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def status(self) -> dict[str, Any]:
        job = self.job
        return job.status() if job is not None else {"state": "idle", "message": "no run yet", "attempt": 0}

    def cancel(self) -> dict[str, Any]:
        job = self.job
        if job is None or job.state != "running":
            raise Busy("no run in progress")
        job.cancel()
        return job.status()

    def result(self, name: Any) -> dict[str, Any]:
        """The run's displacement (mm where it has a scale, else px) and amplitude spectra, by the
        tool's own reading and spectrum (:mod:`flow.figures`); of a run of several regions, the
        first region's (its label says which)."""
        from flow.figures import dominant_frequency, read_measurements

        files = projects.files_of(projects.check_name(name))
        csv_path = self.folder.existing(files["csv"], (".csv",))
        data = read_measurements(csv_path)[0]
        units = "mm" if data["has_mm"] else "px"
        time_s = data["time_s"]
        dx, dy = data[f"dx_{units}"], data[f"dy_{units}"]
        spectra = {}
        for axis, values in (("dx", dx), ("dy", dy)):
            peak, freqs, amplitude = dominant_frequency(time_s, values)
            freqs, amplitude = envelope(freqs, amplitude)
            spectra[axis] = {"peak_hz": peak, "freqs": finite_list(freqs), "amplitude": finite_list(amplitude)}
        with np.errstate(all="ignore"):
            main = "dx" if np.nanstd(dx) >= np.nanstd(dy) else "dy"
        steps = np.diff(time_s[np.isfinite(time_s)])
        nyquist = 0.5 / float(np.median(steps)) if steps.size and np.median(steps) > 0 else None
        peaks = [s["peak_hz"] for s in spectra.values() if s["peak_hz"] is not None]
        view_hz = min(nyquist, max(2.0, 4 * max(peaks))) if peaks and nyquist else nyquist
        present = {role: file for role, file in files.items() if (self.folder.root / file).is_file()}
        return {"name": files["csv"][:-4], "units": units, "label": data["label"], "time_s": finite_list(time_s),
                "dx": finite_list(dx), "dy": finite_list(dy), "spectra": spectra, "main": main,
                "view_hz": view_hz, "files": present,
                "valid": int(np.isfinite(dx).sum()), "frames": len(time_s)}

    def close(self) -> None:
        job = self.job
        if job is not None and job.proc.poll() is None:
            job.cancel()
            try:
                job.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                job.proc.kill()
        if job is not None:
            job.thread.join(timeout=30)  # its staging folder goes with it
        self.frames.close()


class Busy(InputError):
    """A request that conflicts with the run in progress (HTTP 409)."""


def envelope(x: np.ndarray, y: np.ndarray, points: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """At most ``points`` samples of a long spectrum: each bin's largest value (peaks stay)."""
    if len(x) <= points:
        return x, y
    step = int(math.ceil(len(x) / points))
    count = len(x) // step * step
    blocks = y[:count].reshape(-1, step)
    picks = np.nanargmax(np.where(np.isfinite(blocks), blocks, -np.inf), axis=1) + np.arange(0, count, step)
    return x[picks], y[picks]


def retarget_sidecar(path: Path, moved: dict[str, str]) -> None:
    """The sidecar at ``path`` with the paths of files moved since the run (staged masks, from
    ``moved``'s keys to its values) named where they are now."""
    from refflow.io import atomic_path, json_text

    if not moved or not path.is_file():
        return

    def renamed(value: Any) -> Any:
        if isinstance(value, str):
            return moved.get(value, value)
        if isinstance(value, dict):
            return {key: renamed(item) for key, item in value.items()}
        if isinstance(value, list):
            return [renamed(item) for item in value]
        return value

    data = json.loads(path.read_text())
    fixed = renamed(data)
    if fixed != data:
        text = json_text(fixed)
        with atomic_path(path) as tmp:
            tmp.write_text(text)


def write_mask(path: Path, regions: list[dict[str, Any]], frame_size: tuple[int, int]) -> None:
    """A full-frame mask PNG (white inside any region), drawn by the tool's ``--polygon``."""
    import cv2

    from flow.io.frames import Roi
    from flow.measure import poi
    from refflow.io import atomic_path

    width, height = frame_size
    frame = Roi(0, 0, width, height)
    mask = np.zeros((height, width), bool)
    for region in regions:
        text = ",".join(projects._text(v) for point in region["polygon"] for v in point)
        mask |= poi.polygon_mask(text, roi=frame)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), mask.astype(np.uint8) * 255):
            raise OSError(f"cannot write {path}")


class Handler(BaseHTTPRequestHandler):
    server_version = "refflow-gui"
    app: App  # set on the subclass made by make_server

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        if os.environ.get("REFFLOW_GUI_LOG"):
            super().log_message(format, *args)

    # -- replies ------------------------------------------------------------------------------

    def _send(self, status: int, body: bytes, content_type: str, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        fields = {"Content-Type": content_type, "Content-Length": str(len(body)), "Cache-Control": "no-store",
                  "X-Content-Type-Options": "nosniff",
                  "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:",
                  **(headers or {})}
        for key, value in fields.items():
            self.send_header(key, value)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, data: Any, status: int = 200) -> None:
        self._send(status, json.dumps(data, allow_nan=False).encode(), "application/json")

    def _error(self, status: int, message: str, **extra: Any) -> None:
        self._json({"error": " ".join(str(message).split()), **extra}, status)

    def _allowed(self) -> bool:
        """Only this server's own address (a page elsewhere cannot reach it by DNS tricks or
        send it requests from another origin)."""
        port = self.server.server_address[1]
        hosts = {f"127.0.0.1:{port}", f"localhost:{port}"}
        if self.headers.get("Host") not in hosts:
            self._error(403, f"refflow gui answers requests to 127.0.0.1:{port} only")
            return False
        origin = self.headers.get("Origin")
        if origin is not None and origin not in {f"http://{h}" for h in hosts}:
            self._error(403, "requests from another site's page are refused")
            return False
        return True

    # -- routes -------------------------------------------------------------------------------

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        if not self._allowed():
            return
        url = urlsplit(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        app = self.app
        try:
            if url.path in ("/", "/index.html"):
                body, kind = app.statics["index.html"]
                self._send(200, body, kind)
            elif url.path.startswith("/static/"):
                asset = app.statics.get(url.path[len("/static/"):])
                if asset is None:
                    self._error(404, f"{url.path} is not one of the page's files")
                else:
                    self._send(200, asset[0], asset[1])
            elif url.path == "/api/info":
                self._json(app.info())
            elif url.path == "/api/frame":
                self._frame(query.get("i", "0"))
            elif url.path == "/api/run":
                self._json(app.status())
            elif url.path == "/api/result":
                self._json(app.result(query.get("name")))
            elif url.path == "/api/file":
                self._file(query.get("name"), inline=query.get("inline") == "1")
            else:
                self._error(404, f"{url.path} is not part of refflow gui")
        except PathRefused as err:
            self._error(403, str(err))
        except FileNotFoundError as err:
            self._error(404, str(err.args[0] if err.args else err))
        except InputError as err:
            self._error(400, str(err))

    do_HEAD = do_GET

    def do_POST(self) -> None:  # noqa: N802 - http.server's name
        if not self._allowed():
            return
        url = urlsplit(self.path)
        routes = {"/api/project": self.app.save, "/api/pois": self.app.pois, "/api/run": self.app.run,
                  "/api/scale": self.app.scale, "/api/cancel": lambda body: self.app.cancel()}
        if url.path not in routes:
            self._error(404, f"{url.path} is not part of refflow gui")
            return
        if self.headers.get_content_type() != "application/json":
            self._error(415, "send JSON (Content-Type: application/json)")
            return
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if not 0 <= length <= MAX_BODY:
            self._error(413, f"the request body must be JSON of at most {MAX_BODY} bytes")
            return
        try:
            body = json.loads(self.rfile.read(length) or b"{}")
        except ValueError:
            self._error(400, "the request body is not JSON")
            return
        if not isinstance(body, dict):
            self._error(400, "the request body must be a JSON object")
            return
        attempts = {"/api/project": "save", "/api/pois": "pois", "/api/run": "run"}

        def failed(status: int, message: str) -> None:
            # A save, a POI figure or a run that fails is an attempt too: its number lets the
            # page tell its message from an older attempt's.
            kind = attempts.get(url.path)
            extra = {"attempt": self.app._next_attempt(), "kind": kind, "state": "failed"} if kind else {}
            self._error(status, message, **extra)

        try:
            self._json(routes[url.path](body))
        except PathRefused as err:
            failed(403, str(err))
        except Busy as err:
            failed(409, str(err))
        except InputError as err:
            failed(400, str(err))
        except OSError as err:
            failed(500, f"{err.strerror or err}: {err.filename or ''} (check the output folder)")
        except subprocess.TimeoutExpired:
            failed(504, "refflow pois took longer than 10 minutes")

    def _frame(self, text: str) -> None:
        try:
            index = int(text)
        except ValueError:
            self._error(400, f"frame {text!r} is not a frame index")
            return
        if index < 0:
            self._error(400, f"frame {index} is negative")
            return
        blob = self.app.frames.jpeg(index)
        if blob is None:
            self._error(404, f"frame {index} is beyond the video's {self.app.frames.source.frames_read} frames")
            return
        self._send(200, blob, "image/jpeg", {"Cache-Control": "private, max-age=3600"})

    def _file(self, name: Any, *, inline: bool) -> None:
        path = self.app.folder.existing(name, tuple(FILE_TYPES))
        disposition = "inline" if inline else "attachment"
        self._send(200, path.read_bytes(), FILE_TYPES[path.suffix.lower()],
                   {"Content-Disposition": f'{disposition}; filename="{path.name}"'})


def make_server(video: str | Path, out_dir: str | Path, *, port: int = 0, fps: float | None = None,
                calibration: str | Path | None = None) -> ThreadingHTTPServer:
    """A server on 127.0.0.1:``port`` (0: any free port) for ``video``, writing into ``out_dir``;
    its :class:`App` is ``server.app``. Call ``serve_forever()``, then ``shutdown()`` and
    ``server.app.close()``."""
    app = App(video, out_dir, fps=fps, calibration=calibration)
    handler = type("BoundHandler", (Handler,), {"app": app})
    try:
        server = ThreadingHTTPServer(("127.0.0.1", port), handler)
    except OSError as err:
        app.close()
        raise InputError(f"cannot listen on 127.0.0.1:{port} ({err.strerror or err}): another program (another "
                         "refflow gui?) uses it; pass --port with another number, or 0 for any free port") from None
    server.daemon_threads = True
    server.app = app  # type: ignore[attr-defined]
    return server

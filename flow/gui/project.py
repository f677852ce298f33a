"""The project file of ``refflow gui``: what the user chose on the page, as a small JSON.

A project names the video (and its calibration and frame rate), the ROI, the POI regions
(polygons, each with a label) and the mask PNG drawn from them, an optional static
background region and its mask PNG, the scale, the method and its options, and the output
CSV. :func:`track_argv` turns it into the ``refflow track`` argument list that repeats the
run from the shell (``refflow track --project FILE``, or the printed command line).

Paths of the files the page writes (masks, CSV) are stored relative to the project file's
folder, so the folder can be moved; the video and calibration are stored as absolute paths.

Example::

    {"format": "refflow-project/1", "video": "/data/tacoma_bridge.mp4", "fps": null,
     "calibration": null, "roi": [0, 110, 200, 110],
     "regions": [{"label": "deck", "polygon": [[0, 160], [140, 125], [190, 120], [190, 215]]}],
     "mask": "deck_mask.png", "background": null,
     "scale": {"known_length_mm": 11900, "between_px": [10, 140, 190, 121]},
     "method": "dis", "options": {"preset": "fast", "max_frames": 60}, "out": "deck.csv"}
"""

from __future__ import annotations

import math
import re
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from flow.io.errors import InputError
from flow.io.jsonfiles import load_json
from flow.measure.quality import MAX_TYPICAL_SIGMA_PX

FORMAT = "refflow-project/1"

# Project option -> (the `refflow track` flag, its type, the CLI's default: not printed).
OPTIONS: dict[str, tuple[str, type, Any]] = {
    "preset": ("--preset", str, None),
    "reference_frame": ("--reference-frame", int, 0),
    "reference_average": ("--reference-average", int, 1),
    "grid_step": ("--grid-step", int, 1),
    "max_frames": ("--max-frames", int, None),
    "frames": ("--frames", str, None),
    "filter": ("--filter", str, None),
    "threshold_ratio": ("--threshold-ratio", float, 0.5),
    "mcr_threshold": ("--mcr-threshold", float, 0.5),
    "max_typical_sigma": ("--max-typical-sigma", float, MAX_TYPICAL_SIGMA_PX),
    "background_model": ("--background-model", str, "affine"),
    "jobs": ("--jobs", int, None),
}
# Options `refflow pois` takes too (the figure of the POIs next to KLT's corners).
POIS_OPTIONS = ("reference_frame", "reference_average", "grid_step")

# A run's name on the page becomes its files' stem: NAME.csv, NAME.json (the sidecar),
# NAME_project.json, NAME_mask.png, NAME_background.png, NAME_pois.png.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def check_name(name: Any) -> str:
    """``name`` if it is a plain file stem (letters, digits, ``. _ -``), else InputError."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name) or name.endswith("."):
        raise InputError(f"run name {name!r} is not a plain file name: use letters, digits, '.', '_' "
                         "and '-' (no folder: everything goes into the output folder)")
    return name


def files_of(name: str) -> dict[str, str]:
    """The files a run called ``name`` writes, by role, relative to the output folder."""
    name = check_name(name)
    return {"project": f"{name}_project.json", "mask": f"{name}_mask.png",
            "background": f"{name}_background.png", "pois": f"{name}_pois.png",
            "csv": f"{name}.csv", "sidecar": f"{name}.json"}


def foreign_files(folder: Path, name: str) -> list[str]:
    """The files of the run ``name`` in ``folder`` that refflow gui did not write, which it must
    never replace (the user's own ``clip.json`` or ``clip_mask.png`` beside ``clip.mp4``): none
    where the run's project file is a refflow project (the page wrote the run's files), else
    every one of them that exists."""
    files = files_of(name)
    project = folder / files["project"]
    if project.is_file():
        try:
            data = load_json(project, f"project {str(project)!r}")
        except InputError:
            data = None
        if isinstance(data, dict) and data.get("format") == FORMAT:
            return []
    return [file for file in files.values() if (folder / file).exists() or (folder / file).is_symlink()]


def free_name(folder: Path, name: str) -> str:
    """``name``, or ``name_2``, ``name_3``, ... the first whose files refflow gui may write in
    ``folder`` (see :func:`foreign_files`)."""
    for candidate in [name] + [f"{name[:95]}_{k}" for k in range(2, 1000)]:
        if not foreign_files(folder, candidate):
            return candidate
    return name  # the save names the files in the way


def check_files_free(folder: Path, name: str) -> None:
    """InputError where the run ``name`` would replace files in ``folder`` that refflow gui did
    not write."""
    foreign = foreign_files(folder, name)
    if foreign:
        raise InputError(f"{', '.join(foreign)} in {folder} {'was' if len(foreign) == 1 else 'were'} not written by "
                         f"refflow gui, which never replaces such a file: choose another run name (e.g. "
                         f"{free_name(folder, name)}) or another --out-dir")


def _text(value: Any) -> str:
    """A number as the command line spells it (integral floats without '.0', others exact)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)
    return str(value)


def _option(flag: str, value: Any) -> list[str]:
    """``[flag, value]``; ``[flag=value]`` where the value starts with '-' (a point left of or
    above the frame), which argparse would otherwise take for an option."""
    text = _text(value)
    return [f"{flag}={text}"] if text.startswith("-") else [flag, text]


def _number(value: Any, flag: str, kind: type) -> int | float:
    """``value`` (a number or its text, as typed on the page) as ``kind``; argparse's message
    (the CLI's) when it is not one."""
    if isinstance(value, bool):
        value = str(value)
    if kind is int and isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, kind) or (kind is float and isinstance(value, int)):
        return kind(value)
    try:
        return kind(str(value).strip())
    except ValueError:
        raise InputError(f"argument {flag}: invalid {kind.__name__} value: {str(value)!r}") from None


def _points(value: Any, what: str) -> list[list[float]]:
    if not (isinstance(value, list) and all(isinstance(p, list | tuple) and len(p) == 2 for p in value)):
        raise InputError(f"{what} needs a list of [x, y] points, got {str(value)[:80]}")
    points = []
    for x, y in value:
        if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in (x, y)):
            raise InputError(f"{what} holds a point that is not two finite numbers: [{x}, {y}]")
        points.append([round(float(x), 2), round(float(y), 2)])
    return points


def _regions(value: Any, what: str) -> list[dict[str, Any]]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise InputError(f"{what} needs a list of {{'label', 'polygon'}} regions")
    regions = []
    for i, region in enumerate(value):
        if not isinstance(region, dict):
            raise InputError(f"{what} {i + 1} is not a {{'label', 'polygon'}} region")
        label = region.get("label") or f"region {i + 1}"
        if not isinstance(label, str):
            raise InputError(f"{what} {i + 1}: its label must be text")
        polygon = _points(region.get("polygon"), f"{what} {label!r}")
        if len(polygon) < 3:
            raise InputError(f"--polygon of {what} {label!r} needs at least three X,Y vertices")
        regions.append({"label": label[:80], "polygon": polygon})
    return regions


def _roi(value: Any) -> list[int] | None:
    if value in (None, "", []):
        return None
    text = ",".join(map(_text, value)) if isinstance(value, list | tuple) else str(value)
    from flow.io.frames import Roi

    roi = Roi.parse(text.replace(" ", ""))  # the CLI's message for anything but four integers
    return [roi.x, roi.y, roi.width, roi.height]


def _scale(value: Any) -> dict[str, Any] | None:
    """``{"mm_per_px": S}``, ``{"known_length_mm": L, "between_px": [X1, Y1, X2, Y2]}`` or None."""
    if not value:
        return None
    if not isinstance(value, dict):
        raise InputError("scale needs {'mm_per_px': S} or {'known_length_mm': L, 'between_px': [X1, Y1, X2, Y2]}")
    mm_per_px = value.get("mm_per_px")
    if mm_per_px not in (None, "") and not (isinstance(mm_per_px, str) and not mm_per_px.strip()):
        return {"mm_per_px": _number(mm_per_px, "--mm-per-px", float)}
    if "mm_per_px" in value:  # chosen, then left empty: a run in pixels would be a silent surprise
        raise InputError("mm per pixel is empty: type the scale, or choose 'none (pixels only)' to measure "
                         "in pixels")
    if value.get("known_length_mm") in (None, "") and not value.get("between_px"):
        return None
    if value.get("known_length_mm") in (None, "") or not value.get("between_px"):
        raise InputError("--known-length needs --between X1,Y1,X2,Y2 (and vice versa)")
    between = value["between_px"]
    if isinstance(between, list) and len(between) == 2:  # two clicked [x, y] points
        between = [v for point in _points(between, "--between") for v in point]
    if not (isinstance(between, list) and len(between) == 4):
        raise InputError(f"--between {str(between)!r} is not X1,Y1,X2,Y2 (pixel coordinates)")
    return {"known_length_mm": _number(value["known_length_mm"], "--known-length", float),
            "between_px": [_number(v, "--between", float) for v in between]}


def _options(value: Any) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputError("options needs a JSON object of track options")
    options: dict[str, Any] = {}
    for key, item in value.items():
        if key == "params":
            items = item.split("\n") if isinstance(item, str) else item
            if not isinstance(items, list) or not all(isinstance(p, str) for p in items):
                raise InputError("params needs KEY=VALUE lines (method parameters, see `refflow methods`)")
            params = [p.strip() for p in items if p.strip()]
            if params:
                options["params"] = params
            continue
        if key not in OPTIONS:
            raise InputError(f"unknown option {key!r}; known: {', '.join([*OPTIONS, 'params'])}")
        if item is None or item == "":
            continue
        flag, kind, _ = OPTIONS[key]
        options[key] = _number(item, flag, kind) if kind is not str else str(item)
    return options


def from_page(page: dict[str, Any], *, video: str | Path, name: str, fps: float | None = None,
              calibration: str | Path | None = None) -> dict[str, Any]:
    """The project of what the page sent (its ROI, regions, background, scale, method and
    options), for the server's ``video``, ``fps`` and ``calibration``; a run called ``name``.

    Text the user typed is converted here; a value that is not a number gets argparse's message
    (the CLI's). Whether the values make sense (an ROI inside the frame, a positive scale) is for
    ``refflow track`` itself to say, with its own messages.
    """
    if not isinstance(page, dict):
        raise InputError("the page sent no project (a JSON object)")
    files = files_of(name)
    regions = _regions(page.get("regions"), "region")
    background = _regions(page.get("background"), "background region")
    method = page.get("method")
    if method is not None and (not isinstance(method, str) or not method.strip()):
        raise InputError(f"method {method!r} is not a method name (see `refflow methods`)")
    return {
        "format": FORMAT,
        "video": str(Path(video).resolve()),
        "fps": fps,
        "calibration": str(Path(calibration).resolve()) if calibration else None,
        "roi": _roi(page.get("roi")),
        "regions": regions,
        "mask": files["mask"] if regions else None,
        "background": {"regions": background, "mask": files["background"]} if background else None,
        "scale": _scale(page.get("scale")),
        "method": method.strip() if method else None,
        "options": _options(page.get("options")),
        "out": files["csv"],
    }


def dumps(project: dict[str, Any]) -> str:
    """The project as its file holds it: one line per entry, short enough to read and diff."""
    import json

    entries = ",\n".join(f"  {json.dumps(key)}: {json.dumps(value)}" for key, value in project.items())
    return "{\n" + entries + "\n}\n"


def load_project(path: str | Path) -> dict[str, Any]:
    """The project JSON at ``path``, checked (InputError naming the entry otherwise)."""
    path = Path(path)
    name = f"project {str(path)!r}"
    if not path.is_file():
        raise InputError(f"{name} does not exist: save one from `refflow gui` (Save project)")
    data = load_json(path, name)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"{name} is not a refflow project (a JSON object with \"format\": \"{FORMAT}\" "
                         "as `refflow gui` saves it)")
    if not isinstance(data.get("video"), str) or not data["video"]:
        raise InputError(f"{name}: 'video' needs the video's path (text)")
    for key in ("calibration", "mask", "out"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise InputError(f"{name}: {key!r} needs a path (text) or null")
    if not data.get("out"):
        raise InputError(f"{name}: 'out' needs the output CSV's path")
    background = data.get("background")
    if background is not None and not (isinstance(background, dict) and isinstance(background.get("mask"), str)):
        raise InputError(f"{name}: 'background' needs {{'regions': [...], 'mask': PNG}} or null")
    fps = data.get("fps")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, int | float) or not 0 < fps < math.inf):
        raise InputError(f"{name}: 'fps' needs a positive number (frames per second) or null, got {fps!r}")
    try:
        checked = {**data, "roi": _roi(data.get("roi")), "regions": _regions(data.get("regions"), "region"),
                   "scale": _scale(data.get("scale")), "options": _options(data.get("options"))}
    except InputError as err:
        raise InputError(f"{name}: {err}") from None
    method = data.get("method")
    if method is not None and not isinstance(method, str):
        raise InputError(f"{name}: 'method' needs a method name (text) or null")
    return checked


def _input_argv(project: dict[str, Any], base: Path, options: Sequence[str]) -> list[str]:
    """The input options both `track` and `pois` take, paths made absolute against ``base``."""

    def local(path: str) -> str:
        return str(Path(path) if Path(path).is_absolute() else base / path)

    argv = [local(project["video"])]
    if project.get("fps") is not None:
        argv += _option("--fps", project["fps"])
    if project.get("calibration"):
        argv += ["--calibration", local(project["calibration"])]
    if project.get("roi"):
        argv += _option("--roi", ",".join(map(str, project["roi"])))
    if project.get("mask"):
        argv += ["--mask", local(project["mask"])]
    for key in options:
        flag, _, default = OPTIONS[key]
        value = project["options"].get(key)
        if value is not None and value != default:
            argv += _option(flag, value)
    return argv


def track_argv(path: str | Path) -> list[str]:
    """The ``refflow track`` argument list of the project at ``path``, starting with ``"track"``.

    ``flow.cli.main(track_argv(path))`` repeats the project's run; ``"refflow " +
    shlex.join(track_argv(path))`` is its command line. Paths come out absolute. Options left
    at the CLI's defaults are not spelled out. Raises InputError for a project that is
    missing or malformed.
    """
    path = Path(path)
    return track_argv_of(load_project(path), path.resolve().parent)


def track_argv_of(project: dict[str, Any], base: str | Path) -> list[str]:
    """:func:`track_argv` of a checked ``project`` (as :func:`from_page` or :func:`load_project`
    return it) whose file is, or will be, in the folder ``base``."""
    base = Path(base)
    argv = ["track", *_input_argv(project, base, POIS_OPTIONS)]
    if project.get("background"):
        mask = project["background"]["mask"]
        argv += ["--background-mask", str(Path(mask) if Path(mask).is_absolute() else base / mask)]
    scale = project.get("scale")
    if scale and "mm_per_px" in scale:
        argv += _option("--mm-per-px", scale["mm_per_px"])
    elif scale:
        argv += [*_option("--known-length", scale["known_length_mm"]),
                 *_option("--between", ",".join(_text(v) for v in scale["between_px"]))]
    if project.get("method"):
        argv += ["--method", project["method"]]
    for key in (k for k in OPTIONS if k not in POIS_OPTIONS):
        flag, _, default = OPTIONS[key]
        value = project["options"].get(key)
        if value is not None and value != default:
            argv += _option(flag, value)
    for param in project["options"].get("params", []):
        argv += ["--param", param]
    out = project["out"]
    argv += ["--out", str(Path(out) if Path(out).is_absolute() else base / out)]
    return argv


def pois_argv(path: str | Path, out_png: str | Path) -> list[str]:
    """The ``refflow pois`` argument list (starting with ``"pois"``) of the project at ``path``:
    the figure of its POIs next to the corners KLT would use, written to ``out_png``."""
    path = Path(path)
    project = load_project(path)
    return ["pois", *_input_argv(project, path.resolve().parent, POIS_OPTIONS), "--out", str(out_png)]


def command_line(argv: Sequence[str]) -> str:
    """The shell command of a ``refflow`` argument list."""
    return "refflow " + shlex.join(argv)


def command_groups(argv: Sequence[str]) -> list[str]:
    """:func:`command_line` in pieces that belong together: the program and subcommand, each
    positional argument, each option with its value. Joined by spaces they are the command line;
    a page wraps the line between pieces, never inside ``--roi 0,110,200,110``."""
    groups = [f"refflow {shlex.quote(argv[0])}"] if argv else ["refflow"]
    option_open = False  # the last group is an option still waiting for its value
    for item in argv[1:]:
        if option_open and not item.startswith("-"):
            groups[-1] += " " + shlex.quote(item)
            option_open = False
        else:
            groups.append(shlex.quote(item))
            option_open = item.startswith("--") and "=" not in item
    return groups


PROJECT_HELP = ("a project JSON saved by `refflow gui`: its video, ROI, mask, scale, method and options "
                "(further options given here override the project's)")


def expand_project_argv(argv: Sequence[str]) -> list[str]:
    """``refflow`` arguments with ``track --project FILE`` replaced by the project's track
    arguments; options given beside it follow them, so they override the project's (argparse
    keeps an option's last value). Any other argument list comes back unchanged."""
    argv = list(argv)
    if not argv or argv[0] != "track" or not any(a == "--project" or a.startswith("--project=") for a in argv):
        return argv
    rest: list[str] = []
    project = None
    items = iter(argv[1:])
    for item in items:
        if item == "--project":
            project = next(items, None)
            if project is None or project.startswith("-"):
                raise InputError("--project needs FILE: a project JSON saved by `refflow gui`")
        elif item.startswith("--project="):
            project = item.partition("=")[2]
        else:
            rest.append(item)
    return track_argv(project) + rest

"""``refflow field-plot FIELD.h5 --out PREFIX``: pictures of a displacement field file
(:mod:`flow.field.stream`): a map at one frame over the reference image, a movie of the field over
time, with ``--hz F`` the operational deflection shape at F (each pixel's amplitude and
phase at F from its own spectrum), and where the file has each pixel's uncertainty at the map's
frame (``sigma_u_px``, ``sigma_v_px``), its map.

The file is read a frame at a time: the movie is written as it is drawn (MP4), or from at
most :data:`GIF_FRAMES` frames spread over the clip (a GIF is held whole by its writer).
All outputs are written all or nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from flow.field.stream import Field, read_field
from flow.io.errors import InputError
from refflow.io import atomic_paths

COMPONENTS = ("u", "v", "magnitude")
MOVIE_SUFFIXES = (".gif", ".mp4")
#: Frames of a GIF movie at most (spread evenly over the clip); an MP4 takes every frame.
GIF_FRAMES = 150
#: The movie's width at most (px); a narrow box is enlarged to at least MOVIE_MIN_WIDTH.
MOVIE_MAX_WIDTH = 800
MOVIE_MIN_WIDTH = 320
#: The colour scale's limit: this percentile of |value| over the frames looked at.
LIMIT_PERCENTILE = 99.0
#: Frames looked at for the colour scale and the default frame, at most.
SCAN_FRAMES = 200


def _component(field: Field, row: int, component: str) -> np.ndarray:
    if component == "magnitude":
        return np.hypot(field["u_px"][row], field["v_px"][row])
    return field[f"{component}_px"][row]


def _frame_valid(field: Field) -> np.ndarray:
    """Per frame and pixel-column lookup: whether each region's frame is valid (all valid
    where the file has no verdicts, a part's)."""
    if "frame_valid" in field.handle:
        return field["frame_valid"][()].astype(bool)
    return np.ones((field.n_frames, max(len(field["region"][()]), 1)), bool)


def _region_column(field: Field) -> np.ndarray:
    region_map = field["region_map"][()]
    column = np.zeros(region_map.shape, np.intp)
    for k, label in enumerate(field["region"][()]):
        column[region_map == label] = k
    return column


def scan(field: Field, component: str | None) -> tuple[str, float, int]:
    """The component to draw (the one that moves more where not given), its colour limit and
    the frame where it moves most, from at most :data:`SCAN_FRAMES` frames."""
    rows = np.unique(np.linspace(0, field.n_frames - 1, min(field.n_frames, SCAN_FRAMES)).astype(int))
    rms = {"u": np.zeros(len(rows)), "v": np.zeros(len(rows))}
    tops = {"u": [], "v": [], "magnitude": []}
    for k, row in enumerate(rows):
        u, v = field["u_px"][row], field["v_px"][row]
        for name, values in (("u", u), ("v", v), ("magnitude", np.hypot(u, v))):
            finite = values[np.isfinite(values)]
            if finite.size:
                tops[name].append(float(np.percentile(np.abs(finite), LIMIT_PERCENTILE)))
                if name in rms:
                    rms[name][k] = float(np.sqrt(np.mean(finite.astype(np.float64) ** 2)))
    chosen = component or ("u" if rms["u"].max() >= rms["v"].max() else "v")
    limit = max(tops[chosen], default=0.0) or 1e-3
    busiest = rms["u"] ** 2 + rms["v"] ** 2 if chosen == "magnitude" else rms[chosen]
    return chosen, limit, int(rows[int(np.argmax(busiest))])


def _backdrop(field: Field) -> np.ndarray:
    """The reference over the box as grey 0-1 (mid grey where the file has none)."""
    if "reference" not in field.handle:
        return np.full(field["region_map"].shape, 0.5)
    image = field["reference"][()].astype(np.float64)
    low, high = np.percentile(image, [1, 99])
    return np.clip((image - low) / max(high - low, 1e-9), 0, 1)


def _label(component: str) -> str:
    return {"u": "u (x, right) px", "v": "v (y, down) px", "magnitude": "|d| px"}[component]


def _extent(field: Field) -> list[float]:
    x, y = field["x_px"][()], field["y_px"][()]
    return [x[0] - 0.5, x[-1] + 0.5, y[-1] + 0.5, y[0] - 0.5]


def _overlay_figure(field: Field, values: np.ndarray, cmap: str, vmin: float, vmax: float, label: str,
                    title: str, path: Path) -> None:
    """``values`` over the box's pixels drawn over the reference image, with a colour bar."""
    import matplotlib.pyplot as plt

    height, width = values.shape
    size = (min(12.0, max(5.0, width / 100)) + 1.5, min(9.0, max(2.5, height / 100)) + 1.0)
    fig, ax = plt.subplots(figsize=size, dpi=110, layout="constrained")
    extent = _extent(field)
    ax.imshow(_backdrop(field), cmap="gray", vmin=0, vmax=1, extent=extent, interpolation="nearest")
    shown = ax.imshow(np.ma.masked_invalid(values), cmap=cmap, vmin=vmin, vmax=vmax, alpha=0.85, extent=extent,
                      interpolation="nearest")
    fig.colorbar(shown, ax=ax, label=label, shrink=0.9)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(title)
    fig.savefig(path)
    plt.close(fig)


def map_figure(field: Field, row: int, component: str, limit: float, path: Path) -> None:
    """The field at frame ``row`` over the reference image, with a colour bar."""
    cmap, vmin = ("viridis", 0.0) if component == "magnitude" else ("RdBu_r", -limit)
    _overlay_figure(field, _component(field, row, component), cmap, vmin, limit, _label(component),
                    f"{_label(component)} at frame {int(field['frame'][row])} "
                    f"(t = {float(field['time_s'][row]):.4g} s)", path)


def _colour_frame(values: np.ndarray, backdrop: np.ndarray, component: str, limit: float,
                  scale: float) -> np.ndarray:
    """One RGB movie frame: the field's colours blended over the grey reference."""
    import cv2
    from matplotlib import colormaps

    if component == "magnitude":
        cmap, normed = colormaps["viridis"], np.clip(values / limit, 0, 1)
    else:
        cmap, normed = colormaps["RdBu_r"], np.clip(0.5 + 0.5 * values / limit, 0, 1)
    finite = np.isfinite(values)
    rgb = cmap(np.where(finite, normed, 0.5))[..., :3]
    grey = np.repeat(backdrop[..., None], 3, axis=2)
    blended = np.where(finite[..., None], 0.25 * grey + 0.75 * rgb, grey)
    image = np.clip(np.rint(blended * 255), 0, 255).astype(np.uint8)
    if scale != 1.0:
        image = cv2.resize(image, None, fx=scale, fy=scale,
                           interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)
    return image


def _caption(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    band = np.full((22, image.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    framed = np.vstack([band, image])
    # Even sizes: H.264 needs them.
    return framed[: framed.shape[0] // 2 * 2, : framed.shape[1] // 2 * 2]


def movie(field: Field, component: str, limit: float, path: Path, *, fps: float) -> int:
    """The field over time, a frame at a time; returns the frames written."""
    import imageio.v2 as imageio

    backdrop = _backdrop(field)
    width = backdrop.shape[1]
    scale = min(MOVIE_MAX_WIDTH / width, max(1.0, MOVIE_MIN_WIDTH / width))
    gif = path.suffix.lower() == ".gif"
    rows = (np.unique(np.linspace(0, field.n_frames - 1, min(field.n_frames, GIF_FRAMES)).astype(int)) if gif
            else np.arange(field.n_frames))
    if gif:
        writer = imageio.get_writer(path, format="GIF", mode="I", duration=1000.0 / fps, loop=0)
    else:
        writer = imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=7,
                                    macro_block_size=1)
    sign = "0.." if component == "magnitude" else "+/-"
    with writer:
        for row in rows:
            image = _colour_frame(_component(field, int(row), component), backdrop, component, limit, scale)
            writer.append_data(_caption(image, f"{component} frame {int(field['frame'][row])} "
                                               f"t={float(field['time_s'][row]):.4g}s  colour {sign}{limit:.3g} px"))
    return len(rows)


def deflection_shape(field: Field, hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's amplitude (px) and phase (deg) of u and v at ``hz``: the Fourier
    coefficient of its mean-free series over the frames where it is finite and its region's
    frame valid (times from ``time_s``, uneven clocks included), accumulated a frame at a time."""
    times = field["time_s"][()]
    valid = _frame_valid(field)
    column = _region_column(field)
    shape = column.shape
    sums = {name: (np.zeros(shape, complex), np.zeros(shape), np.zeros(shape, complex), np.zeros(shape))
            for name in ("u_px", "v_px")}
    for row, t in enumerate(times):
        phasor = np.exp(-2j * np.pi * hz * t)
        ok_frame = valid[row][column]
        for name, (coefficient, total, weights, count) in sums.items():
            values = field[name][row].astype(np.float64)
            ok = np.isfinite(values) & ok_frame
            values = np.where(ok, values, 0.0)
            coefficient += values * phasor
            total += values
            weights += ok * phasor
            count += ok
    out = []
    for coefficient, total, weights, count in sums.values():
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = total / count
            spectrum = (coefficient - mean * weights) * 2.0 / count
        spectrum[count < 4] = np.nan
        out.append(spectrum)
    spectra = out
    # Phases relative to the pixel that moves most (in and out of phase read at a glance).
    magnitude = np.hypot(np.abs(spectra[0]), np.abs(spectra[1]))
    if np.isfinite(magnitude).any():
        at = np.unravel_index(np.nanargmax(magnitude), magnitude.shape)
        main = spectra[0] if abs(spectra[0][at]) >= abs(spectra[1][at]) else spectra[1]
        turn = np.exp(-1j * np.angle(main[at]))
        spectra = [s * turn for s in spectra]
    return (np.abs(spectra[0]), np.degrees(np.angle(spectra[0])), np.abs(spectra[1]),
            np.degrees(np.angle(spectra[1])))


def deflection_figure(field: Field, hz: float, path: Path) -> None:
    import matplotlib.pyplot as plt

    amp_u, phase_u, amp_v, phase_v = deflection_shape(field, hz)
    top = float(np.nanmax([np.nanmax(amp_u), np.nanmax(amp_v), 1e-9]))
    height, width = amp_u.shape
    size = (2 * (min(7.0, max(3.5, width / 120)) + 1.2), 2 * (min(5.0, max(1.8, height / 120)) + 0.8))
    fig, axes = plt.subplots(2, 2, figsize=size, dpi=100, layout="constrained")
    extent = _extent(field)
    backdrop = _backdrop(field)
    for (ax_amp, ax_phase), amp, phase, name in ((axes[0], amp_u, phase_u, "u"), (axes[1], amp_v, phase_v, "v")):
        for ax in (ax_amp, ax_phase):
            ax.imshow(backdrop, cmap="gray", vmin=0, vmax=1, extent=extent, interpolation="nearest")
        shown = ax_amp.imshow(np.ma.masked_invalid(amp), cmap="viridis", vmin=0, vmax=top, extent=extent,
                              interpolation="nearest")
        fig.colorbar(shown, ax=ax_amp, label=f"amplitude of {name} (px)")
        # Where the pixel hardly moves at F its phase is noise: drawn faint.
        faint = np.where(amp >= 0.2 * top, 1.0, 0.25)
        shown = ax_phase.imshow(np.ma.masked_invalid(phase), cmap="twilight", vmin=-180, vmax=180, extent=extent,
                                alpha=np.where(np.isfinite(phase), faint, 0.0), interpolation="nearest")
        fig.colorbar(shown, ax=ax_phase, label=f"phase of {name} (deg)")
        ax_amp.set_title(f"{name}: amplitude at {hz:g} Hz")
        ax_phase.set_title(f"{name}: phase (0 = the pixel moving most)")
    fig.suptitle(f"Operational deflection shape at {hz:g} Hz")
    fig.savefig(path)
    plt.close(fig)


def _check_hz(field: Field, hz: float) -> None:
    times = field["time_s"][()]
    if not (np.isfinite(hz) and hz > 0):
        raise InputError(f"--hz {hz:g} is not a frequency > 0 in Hz")
    if len(times) < 4:
        raise InputError(f"the field has {len(times)} frames: a deflection shape needs at least 4")
    step = float(np.median(np.diff(times)))
    nyquist = 0.5 / step if step > 0 else 0.0
    if hz >= nyquist:
        raise InputError(f"--hz {hz:g} is at or above the Nyquist frequency {nyquist:.4g} Hz of the field's "
                         f"{1 / step:.4g} frames per second: pick a lower frequency")


def outputs_of(prefix: str, movie_format: str = "gif", hz: float | None = None) -> list[Path]:
    """The pictures ``plot`` writes whatever the file holds (``PREFIX_sigma.png`` comes on top
    where it has each pixel's uncertainty)."""
    outputs = [Path(f"{prefix}_map.png"), Path(f"{prefix}_field.{movie_format}")]
    if hz is not None:
        outputs.append(Path(f"{prefix}_ods.png"))
    return outputs


def plot(path: str, prefix: str, *, frame: int | None = None, component: str | None = None, hz: float | None = None,
         movie_format: str = "gif", fps: float = 10.0) -> list[Path]:
    """Write the map, the movie and (with ``hz``) the deflection shape; returns the files."""
    from flow.outputs import check_outputs

    if component is not None and component not in COMPONENTS:
        raise InputError(f"--component {component!r} is not one of {', '.join(COMPONENTS)}")
    if f".{movie_format}" not in MOVIE_SUFFIXES:
        raise InputError(f"--movie {movie_format!r} is not gif or mp4")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"--movie-fps {fps:g} must be > 0")
    outputs = outputs_of(prefix, movie_format, hz)
    with read_field(path) as field:
        check_outputs(outputs, [("the field file", Path(path))], option="--out")
        frames = field["frame"][()]
        if field.n_frames == 0:
            raise InputError(f"{path} holds no frame")
        if frame is not None and frame not in frames:
            raise InputError(f"--frame {frame} is not in the field (frames {int(frames[0])}..{int(frames[-1])})")
        if hz is not None:
            _check_hz(field, hz)
        chosen, limit, busiest = scan(field, component)
        row = busiest if frame is None else int(np.flatnonzero(frames == frame)[0])
        sigma = _pixel_sigma(field, row)
        if sigma is not None:
            outputs.append(Path(f"{prefix}_sigma.png"))
            check_outputs(outputs[-1:], [("the field file", Path(path))], option="--out")
        with atomic_paths(*outputs) as written:
            map_figure(field, row, chosen, limit, written[0])
            movie(field, chosen, limit, written[1], fps=fps)
            if hz is not None:
                deflection_figure(field, hz, written[2])
            if sigma is not None:
                sigma_figure(field, row, sigma, written[-1])
    return outputs


def _pixel_sigma(field: Field, row: int) -> np.ndarray | None:
    """The uncertainty of each pixel's displacement vector at frame ``row`` (px), None where the
    file has none there."""
    if "sigma_u_px" not in field.handle or "sigma_v_px" not in field.handle:
        return None
    sigma = np.hypot(field["sigma_u_px"][row].astype(np.float64), field["sigma_v_px"][row].astype(np.float64))
    return sigma if np.isfinite(sigma).any() else None


def sigma_figure(field: Field, row: int, sigma: np.ndarray, path: Path) -> None:
    """Each pixel's standard uncertainty at frame ``row`` over the reference image."""
    top = float(np.percentile(sigma[np.isfinite(sigma)], LIMIT_PERCENTILE)) or 1e-3
    _overlay_figure(field, sigma, "magma", 0.0, top, "sigma of the displacement, px",
                    f"sigma (noise) at frame {int(field['frame'][row])}, median {float(np.nanmedian(sigma)):.2g} px",
                    path)


def cmd_field_plot(args: argparse.Namespace) -> int:
    written = plot(args.field, args.out, frame=args.frame, component=args.component, hz=args.hz,
                   movie_format=args.movie, fps=args.movie_fps)
    print(f"refflow field-plot: -> {', '.join(map(str, written))}", file=sys.stderr)
    return 0


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``refflow field-plot`` to the ``refflow`` subcommands; returns its parser."""
    p = subparsers.add_parser(
        "field-plot", help="map, movie and deflection shape of a displacement field (track --field)",
        description="Pictures of a `refflow track --field` file: PREFIX_map.png (the field at one frame over "
                    "the reference image), PREFIX_field.gif or .mp4 (the field over time), with --hz "
                    "PREFIX_ods.png (each pixel's amplitude and phase at that frequency), and where the file "
                    "has each pixel's uncertainty at the map's frame, PREFIX_sigma.png.")
    p.add_argument("field", help="a field file written by `refflow track --field`")
    p.add_argument("--out", required=True, metavar="PREFIX", help="prefix of the pictures written")
    p.add_argument("--frame", type=int, help="video frame index of the map (default: the frame moving most)")
    p.add_argument("--component", choices=COMPONENTS, help="what is drawn (default: u or v, whichever moves more)")
    p.add_argument("--hz", type=float, help="draw the operational deflection shape at this frequency (Hz)")
    p.add_argument("--movie", choices=("gif", "mp4"), default="gif",
                   help=f"movie format (gif: at most {GIF_FRAMES} frames spread over the clip; mp4: every frame)")
    p.add_argument("--movie-fps", type=float, default=10.0, help="movie frames per second (default 10)")
    p.set_defaults(func=cmd_field_plot)
    return p

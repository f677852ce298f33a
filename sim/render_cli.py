"""Command line for the renderer (wired as ``python -m sim render``).

Usage::

    python -m sim.render_cli --config CONFIG --shapes SHAPES.npz --out-dir DIR \
        [--full-frame] [--max-frames N] [--no-progress]
    python -m sim.render_cli calibration --config CONFIG --out-dir DIR [--n-images 15] [--board 9x6] [--square-mm 40]
    python -m sim.render_cli figures --config CONFIG [--shapes SHAPES.npz] [--out-dir results/figures]
    python -m sim.render_cli synthetic-shapes --out SHAPES.npz [--duration-s 2]
    python -m sim.render_cli regions --config CONFIG --out REGIONS.png

Exit codes: 0 success, 2 bad input (message on stderr).
"""

from __future__ import annotations

import argparse
import sys

from refflow.config import load_config


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m sim.render_cli",
                                 description="Render the synthetic phone video of the beam.")
    sub = ap.add_subparsers(dest="command")
    ap.add_argument("--config")
    ap.add_argument("--shapes")
    ap.add_argument("--out-dir")
    ap.add_argument("--full-frame", action="store_true", help="whole 4K sensor instead of the crop")
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--no-progress", action="store_true")
    cal = sub.add_parser("calibration", help="checkerboard images through the same camera")
    cal.add_argument("--config")
    cal.add_argument("--out-dir", required=True)
    cal.add_argument("--n-images", type=int, default=15)
    cal.add_argument("--board", default="9x6", help="inner corners COLSxROWS (as refflow calibrate --board)")
    cal.add_argument("--square-mm", type=float, default=40.0, help="square side in mm")
    cal.add_argument("--no-progress", action="store_true")
    fig = sub.add_parser("figures", help="render_full/crop/occluded PNGs (and render_occluding.png)")
    fig.add_argument("--config")
    fig.add_argument("--shapes", help="default: the analytic 4 Hz first mode")
    fig.add_argument("--out-dir", default="results/figures")
    reg = sub.add_parser("regions", help="labelled mask of the sensor's heights on the video's window "
                         "(grey value k = the k-th height, sorted; config section `regions`)")
    reg.add_argument("--config", required=True)
    reg.add_argument("--out", required=True, help="PNG to write")
    syn = sub.add_parser("synthetic-shapes", help="analytic first-mode shapes.npz for development")
    syn.add_argument("--out", required=True)
    syn.add_argument("--duration-s", type=float, default=2.0)
    syn.add_argument("--freq-hz", type=float, default=4.0)
    syn.add_argument("--peak-mm", type=float, default=1.8)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from sim.scene import BeamShapes, synthetic_shapes, write_synthetic_shapes
    try:
        if args.command == "synthetic-shapes":
            write_synthetic_shapes(args.out, duration_s=args.duration_s, freq_hz=args.freq_hz,
                                   peak_mm=args.peak_mm)
            print(args.out)
            return 0
        config = load_config(args.config) if args.config else {}
        if args.command == "regions":
            from sim.masks import write_regions
            info = write_regions(config, args.out)
            spans = ", ".join(f"{h:g} mm: rows {a}-{b}" for h, (a, b) in zip(info["heights_mm"], info["rows"], strict=True))
            print(f"{args.out}: {len(info['heights_mm'])} regions ({spans})")
            return 0
        if args.command == "calibration":
            from sim.calibration import render_calibration
            try:
                cols, rows = (int(v) for v in args.board.lower().split("x"))
            except ValueError:
                raise ValueError(f"--board {args.board!r} is not COLSxROWS, e.g. 9x6") from None
            if cols < 2 or rows < 2 or not args.square_mm > 0:
                raise ValueError(f"--board {args.board!r} needs >= 2x2 inner corners and --square-mm > 0")
            meta = render_calibration(config, args.out_dir, n_images=args.n_images, cols=cols, rows=rows,
                                      square_mm=args.square_mm, progress=not args.no_progress)
            print(f"{len(meta['images'])} images in {args.out_dir}")
            return 0
        if args.command == "figures":
            from sim.figures import render_figures
            from sim.occlusion import OcclusionConfig
            occ = OcclusionConfig.from_config(config)
            # the analytic mode, long enough for the config's occlusion
            shapes = (BeamShapes.load(args.shapes) if args.shapes else BeamShapes(
                **synthetic_shapes(duration_s=max(2.0, occ.start_s + occ.duration_s + 1.0))))
            for path in render_figures(config, shapes, args.out_dir):
                print(path)
            return 0
        if not args.shapes or not args.out_dir:
            raise ValueError("render needs --shapes SHAPES.npz and --out-dir DIR")
        if args.max_frames is not None and args.max_frames < 1:
            raise ValueError(f"--max-frames must be >= 1, got {args.max_frames}")
        from sim.clip import render_clip
        meta = render_clip(config, BeamShapes.load(args.shapes), args.out_dir,
                           full_frame=args.full_frame, max_frames=args.max_frames,
                           progress=not args.no_progress)
        t = meta["timings"]
        print(f"{meta['frames']} frames {meta['crop']['width']}x{meta['crop']['height']} -> "
              f"{args.out_dir}/{meta['video']} ({t['fps_rendered']:.2f} frames/s)")
        return 0
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

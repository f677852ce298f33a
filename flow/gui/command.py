"""``refflow gui``'s subcommand: its arguments (:func:`add_parser`, the one thing the CLI
imports) and :func:`cmd_gui`, which serves the page until Ctrl-C (the server is imported only
when ``gui`` runs)."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

DEFAULT_PORT = 8765


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``gui`` subcommand to ``refflow``'s subparsers (its ``func`` is :func:`cmd_gui`)."""
    p = subparsers.add_parser("gui", help="a page in the browser: draw the ROI, mask and scale, run track, "
                              "plot the result")
    p.add_argument("input", help="video file, folder of images or camera recording (as for `refflow track`)")
    p.add_argument("--out-dir", help="the only folder the page writes in: project JSON, masks, CSV and "
                   "sidecar (default: ./<video name>_refflow)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT,
                   help=f"port on 127.0.0.1 (default {DEFAULT_PORT}; 0: any free port)")
    p.add_argument("--no-browser", action="store_true", help="print the page's address, open no browser")
    p.add_argument("--calibration", help="calibration JSON from `refflow calibrate`: scale points are undistorted "
                   "and the runs use it")
    p.add_argument("--fps", type=float, help="frame rate of an image folder (required to run there); on a video, "
                   "the capture rate where it differs from the file's (passed to track)")
    p.set_defaults(func=cmd_gui)
    return p


def default_out_dir(video: str | Path) -> Path:
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", Path(video).name.split(".")[0]) or "video"
    return Path.cwd() / f"{stem}_refflow"


def cmd_gui(args: argparse.Namespace) -> int:
    """Serve the page until Ctrl-C; a run in progress is cancelled (its files removed)."""
    from flow.gui.server import make_server
    from flow.io.errors import InputError

    if args.port is not None and not 0 <= args.port <= 65535:
        raise InputError(f"--port {args.port} is not a port number (0-65535)")
    if args.fps is not None and not args.fps > 0:
        raise InputError(f"--fps {args.fps} is not a finite positive number: pass the camera frame rate in frames per second")
    out_dir = Path(args.out_dir) if args.out_dir else default_out_dir(args.input)
    server = make_server(args.input, out_dir, port=args.port, fps=args.fps, calibration=args.calibration)
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    print(f"refflow gui: {url} (Ctrl-C stops it); files go to {server.app.folder.root}", flush=True)
    if not args.no_browser:
        import webbrowser

        if not webbrowser.open(url):
            print("refflow gui: no browser found: open the address above", file=sys.stderr)
    try:
        server.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        print("refflow gui: stopped", file=sys.stderr)
    finally:
        server.server_close()
        server.app.close()
    return 0

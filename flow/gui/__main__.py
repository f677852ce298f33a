"""``python -m flow.gui VIDEO [options]``: the same as ``refflow gui VIDEO [options]``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from flow.gui import add_parser


def main(argv: Sequence[str] | None = None) -> int:
    from flow.io import InputError, quiet_decoder_logs

    quiet_decoder_logs()
    parser = argparse.ArgumentParser(prog="refflow")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["gui", *(sys.argv[1:] if argv is None else argv)])
    try:
        return args.func(args)
    except InputError as err:
        print(f"refflow gui: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""``python -m flow.gui VIDEO [options]``: the same as ``refflow gui VIDEO [options]``."""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    from flow.cli import main as refflow

    return refflow(["gui", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())

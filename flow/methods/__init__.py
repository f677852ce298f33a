"""Built-in methods; importing a module registers its methods."""

from __future__ import annotations

import importlib

from flow.methods import klt, opencv_dense  # noqa: F401

DEEPFLOW_IMPORT_ERROR: str | None = None
try:  # the clean-room DeepMatching + DeepFlow lands separately
    importlib.import_module("flow.methods.deepflow")
except ImportError as err:
    DEEPFLOW_IMPORT_ERROR = str(err)

"""Scenario configs: defaults merged with one scenario's overrides.

``python -m refflow.config --json TEXT --out FILE`` writes a merged scenario
config as YAML (the workflow's first step for every scenario).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from refflow.io import atomic_path


def deep_merge(base: Mapping[str, Any], override: Mapping[str, Any] | None) -> dict[str, Any]:
    """Return ``base`` with ``override`` laid over it; lists are replaced whole."""
    merged = copy.deepcopy(dict(base))
    for key, value in (override or {}).items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def load_config(path: str | Path) -> dict[str, Any]:
    """Read a config file: YAML, or JSON where the name ends in ``.json`` (parsed as JSON,
    whose numbers YAML 1.1 can read differently: ``1e5`` is a string there). The one loader
    of every package's configs (scenario configs, stage configs, gates); an empty file is an
    empty mapping. A ``ValueError`` naming the file and what is wrong with it otherwise.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config file {path} does not exist")
    text = path.read_text()
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (yaml.YAMLError, json.JSONDecodeError) as err:
        kind = "JSON" if path.suffix == ".json" else "YAML"
        raise ValueError(f"config file {path} is not valid {kind}: {err}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"config file {path} must hold a mapping at the top level, got {type(data).__name__}")
    return data


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m refflow.config", description=__doc__)
    parser.add_argument("--json", required=True, help="the merged scenario config as JSON text")
    parser.add_argument("--out", required=True, help="YAML file to write")
    args = parser.parse_args(argv)
    try:
        data = json.loads(args.json)
    except json.JSONDecodeError as err:
        print(f"error: --json is not valid JSON: {err}", file=sys.stderr)
        return 2
    with atomic_path(args.out) as tmp:
        tmp.write_text(yaml.safe_dump(data, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Same input, same bytes, whether numba compiles the kernels afresh or loads them from its
cache: the first run on a fresh machine (``make all`` from a clean clone) must give the numbers
of every later run. With ``fastmath`` (LLVM may reassociate floating-point sums) a freshly
compiled ``refine`` differed from the cached one by about 1e-4 px."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = r"""
import hashlib
import numpy as np
from flow.methods.deepflow.deepmatching import deep_matching
from flow.methods.deepflow.variational import VariationalParams, refine

rng = np.random.default_rng(3)
y, x = np.mgrid[0:96, 0:128].astype(np.float32)
reference = (120 + 40 * np.sin(x / 7.0) * np.cos(y / 9.0) + rng.normal(0, 2, x.shape)).astype(np.float32)
current = np.roll(reference, 2, axis=1) + rng.normal(0, 2, x.shape).astype(np.float32)
flow = refine(reference, current, VariationalParams())
grid = deep_matching(reference, current)
digest = hashlib.md5(flow.tobytes())
for name in sorted(vars(grid)):
    value = getattr(grid, name)
    if isinstance(value, np.ndarray):
        digest.update(np.ascontiguousarray(value).tobytes())
print(digest.hexdigest())
"""


def test_cold_and_cached_kernels_give_the_same_bytes(tmp_path: Path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "NUMBA_NUM_THREADS": "1"}
    root = Path(__file__).resolve().parents[2]
    runs = [subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=root, capture_output=True, text=True,
                           check=True).stdout.strip() for _ in range(2)]
    assert any((tmp_path / "numba").rglob("*.nbi")), "the first run left no cache: the test tests nothing"
    assert runs[0] == runs[1], "freshly compiled and cached kernels disagree"

"""Where outputs go (issue 32, cases 7-9): an output that is a folder, a full disk, a figure
name without a format, a sidecar that is somebody else's or another output's, and two runs
that would share one sidecar. Each is one line, exit 2, before any work where it can be
known then, and no file left behind."""

from __future__ import annotations

import csv
import errno
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flow.cli import main

W, H = 96, 64


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("outputs_frames")
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)), (0, 0), 2.0)
    for i in range(3):
        cv2.imwrite(str(folder / f"f{i}.png"), np.clip(np.roll(base, i, axis=1), 0, 255).astype(np.uint8))
    return folder


def track(frames: Path, *extra: str) -> int:
    return main(["track", str(frames), "--fps", "30", "--rect", "20,10,50,40", "--method", "dis",
                 "--no-progress", *extra])


def one_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and "Traceback" not in err, err
    return errors[0]


def never_measured(monkeypatch) -> None:
    """Make measuring a frame fail the test: the refusal must come first."""
    from flow.measure import driver

    def measured(*args, **kwargs):
        raise AssertionError("a frame was measured before the refusal")

    monkeypatch.setattr(driver, "track_dense", measured)


# -- case 7: an output that is a folder; a full disk ----------------------------------------------


@pytest.mark.parametrize("folder", ["o.csv", "o.json"])
def test_an_output_or_sidecar_that_is_a_folder_is_refused_before_measuring(frames, tmp_path, monkeypatch,
                                                                             capsys, folder) -> None:
    (tmp_path / folder).mkdir()
    never_measured(monkeypatch)
    assert track(frames, "--out", str(tmp_path / "o.csv")) == 2
    line = one_error(capsys)
    assert f"output {tmp_path / folder} is an existing folder, not a file: choose another --out" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == [folder]


@pytest.mark.parametrize("failing", ["sidecar", "csv", "raw"])
def test_a_full_disk_names_the_file_that_could_not_be_written(frames, tmp_path, monkeypatch, capsys,
                                                              failing) -> None:
    """ENOSPC carries no file name (the message was 'No space left on device:  (check the
    path and permissions)'): the line names the output, not its temporary, and nothing stays."""
    from flow.measure import formats
    from refflow import trackcsv

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    out, raw = tmp_path / "o.csv", tmp_path / "o.npz"
    if failing == "sidecar":
        original = Path.write_text
        monkeypatch.setattr(Path, "write_text", lambda self, *a, **k: full() if self.name.endswith(".part.json")
                            else original(self, *a, **k))
    elif failing == "csv":
        monkeypatch.setattr(trackcsv, "write", full)
    else:
        monkeypatch.setattr(formats, "save_raw_tracks", full)
    assert track(frames, "--out", str(out), "--raw-tracks", str(raw)) == 2
    expected = {"sidecar": out.with_suffix(".json"), "csv": out, "raw": raw}[failing]
    assert one_error(capsys).endswith(f"error: No space left on device: could not write {expected} "
                                      "(free space on that disk, or choose another --out)")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_while_measuring_names_the_store_folder(frames, tmp_path, monkeypatch, capsys) -> None:
    from flow.measure import storage

    def full(self, dx, dy):
        with self._named():
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(storage.PoiStore, "extend", full)
    assert track(frames, "--out", str(tmp_path / "o.csv")) == 2
    line = one_error(capsys)
    assert f"could not write {tmp_path} (the run's per-POI store, beside the output)" in line
    assert list(tmp_path.iterdir()) == []


# -- case 8: a figure's name must say its format ------------------------------------------------


@pytest.fixture(scope="module")
def measured_csv(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("plot") / "ok.csv"
    time_s = np.arange(60) / 30.0
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid"])
        for i, t in enumerate(time_s):
            writer.writerow([i, t, np.sin(2 * np.pi * 2 * t), 0.0, "nan", "nan", 1])
    return path


@pytest.mark.parametrize("name", ["myplot", "plot.txt", "plot.json", "plot.csv"])
def test_plot_refuses_a_name_without_a_figure_format(measured_csv, tmp_path, capsys, name) -> None:
    out = tmp_path / name
    assert main(["plot", str(measured_csv), "--out", str(out)]) == 2
    said = "has no extension" if not out.suffix else f"ends in '{out.suffix}'"
    assert f"--out {out} {said}: the format is taken from the name; name it .png, .pdf or .svg" in one_error(capsys)
    assert list(tmp_path.iterdir()) == []


def test_plot_writes_each_format_it_names(measured_csv, tmp_path, capsys) -> None:
    for suffix in (".png", ".pdf", ".svg"):
        assert main(["plot", str(measured_csv), "--out", str(tmp_path / f"p{suffix}")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.pdf", "p.png", "p.svg"]


@pytest.mark.parametrize("name", ["poisout", "pois.txt", "pois.json"])
def test_pois_refuses_a_name_without_an_image_format(frames, tmp_path, capsys, name) -> None:
    out = tmp_path / name
    assert main(["pois", str(frames), "--fps", "30", "--rect", "20,10,50,40", "--out", str(out)]) == 2
    assert "name it .png, .jpg, .jpeg, .tif or .tiff" in one_error(capsys)
    assert list(tmp_path.iterdir()) == []
    assert main(["pois", str(frames), "--fps", "30", "--rect", "20,10,50,40", "--out", str(tmp_path / "p.png")]) == 0


# -- case 9: the sidecar is the output's own; two runs never share one -------------------------------


def test_an_unrelated_json_is_never_replaced_by_a_sidecar(frames, tmp_path, monkeypatch, capsys) -> None:
    mine = tmp_path / "o.json"
    for text in ('{"my": "settings"}', "not json at all", '{"tool": "refflow track"}'):
        mine.write_text(text)
        never_measured(monkeypatch)
        assert track(frames, "--out", str(tmp_path / "o.csv")) == 2
        assert f"{mine} exists and is not a refflow sidecar: refflow never replaces a file it did not write" \
            in one_error(capsys)
        assert mine.read_text() == text and sorted(p.name for p in tmp_path.iterdir()) == ["o.json"]


def test_a_rerun_replaces_its_own_sidecar_but_not_another_outputs(frames, tmp_path, capsys) -> None:
    """``--out a.csv`` then ``--out a.csv`` again: replaced, said on the console. ``--out a``
    would describe itself in a.json too: refused, a.csv's sidecar kept."""
    out = tmp_path / "a.csv"
    assert track(frames, "--out", str(out)) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["csv"] == "a.csv"
    capsys.readouterr()
    assert track(frames, "--out", str(out)) == 0
    assert f"replaced the earlier {out}, {out.with_suffix('.json')}" in capsys.readouterr().err
    before = out.with_suffix(".json").read_bytes()
    assert track(frames, "--out", str(tmp_path / "a")) == 2
    assert (f"{tmp_path / 'a.json'} is the sidecar of {out}, not of {tmp_path / 'a'}: outputs whose names "
            "differ only in their extension share one sidecar") in one_error(capsys)
    assert out.with_suffix(".json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "a.json"]


def test_two_runs_sharing_a_sidecar_cannot_run_at_once(frames, tmp_path, capsys) -> None:
    """``--out a`` and ``--out a.csv`` at the same time: both claim ``a.json``, so the second
    is refused, naming the first's process (here a live process holding the claim)."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    lock = tmp_path / ".a.json.refflow-lock"
    try:
        lock.write_text(str(other.pid))
        assert track(frames, "--out", str(tmp_path / "a.csv")) == 2
        line = one_error(capsys)
        assert f"another refflow run (process {other.pid}) is writing {tmp_path / 'a.json'}" in line
    finally:
        other.kill()
        other.wait()
    lock.unlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# -- the property: whatever --out names, a measurement or one line, never a stray file -----------------

names = st.one_of(
    st.sampled_from(["o", "o.csv", "o.json", "o.txt", "dir", "dir.csv", "dir/o.csv", "file/o.csv", "o.npz",
                     "mine", "mine.csv", "f0.png"]),
    st.text(st.sampled_from("abc._-"), min_size=1, max_size=6).filter(lambda n: n not in (".", "..")))


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=names, raw=st.booleans())
def test_any_output_name_measures_or_refuses_in_one_line(frames, tmp_path, capsys, name, raw) -> None:
    """A folder ``dir``, a file ``file``, the user's own ``mine.json`` and an input image sit in
    the folder: whatever --out names, the run measures (its CSV and sidecar, the sidecar naming
    the CSV) or refuses in one line, and no other file appears or changes."""
    work = tmp_path / "work"
    if work.exists():
        import shutil

        shutil.rmtree(work)
    work.mkdir()
    (work / "dir").mkdir()
    (work / "dir.json").mkdir()
    (work / "file").write_text("a file")
    (work / "mine.json").write_text('{"mine": true}')
    before = {p: (p.read_bytes() if p.is_file() else None) for p in work.rglob("*")}
    out = work / name
    extra = ["--raw-tracks", str(work / "part.npz")] if raw else []
    rc = track(frames, "--out", str(out), *extra)
    err = capsys.readouterr().err
    assert rc in (0, 2) and "Traceback" not in err, err
    after = {p: (p.read_bytes() if p.is_file() else None) for p in work.rglob("*")}
    for path, content in before.items():
        assert after.get(path, "gone") == content, (name, path, err)
    new = sorted(str(p.relative_to(work)) for p in set(after) - set(before))
    if rc == 2:
        assert len([line for line in err.splitlines() if ": error: " in line]) == 1, err
        assert new == [], (name, new)
    else:
        sidecar = out.with_suffix(".json")
        expected = sorted({str(out.relative_to(work)), str(sidecar.relative_to(work))}
                          | ({"part.npz"} if raw else set()))
        assert new == expected, (name, new, err)
        assert json.loads(sidecar.read_text())["csv"] == out.name

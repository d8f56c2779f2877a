"""Paths and damaged inputs that came from a data folder, not from the user's own command line.

Before: a measured set's ``difference`` / ``difference_se`` columns and ``images`` /
``background`` globs (gap diagnose, ``infer --csv``, ``calibrate --camera-csv``) accepted
absolute paths and ``..`` (a decoy ``.npy`` outside the folder was used, ``/etc/*`` was
listed); ids with ``/`` crashed after the work; a PNG header claiming 100000x100000 px, a
calibration with a NaN slope or ``feature_settings`` of the wrong type, a CSV naming ``O3``
twice, an empty CSV were accepted or ended in tracebacks; ``gap synth --overwrite`` deleted
files the user had added.  Now each is one :class:`UserError` naming the parameter (and the
switch that allows reading outside the folder), raised before any solve.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from elastimap.camera import calibration as C
from elastimap.camera.frames import expand, read_frame
from elastimap.dataset.phantoms import read_phantoms
from elastimap.errors import UserError
from elastimap.gap import measured, synth
from elastimap.gap.simulate import Simulator


@pytest.fixture(scope="module")
def mset(tmp_path_factory):
    """A SYNTHETIC measured set (analytic TOY backend, not physics) in its folder."""
    d = tmp_path_factory.mktemp("m") / "M"
    meas, truth = synth.synthesize(synth.phantom_design(6, 0), [], Simulator(None, "tiny", "toy"), frames=3, seed=1)
    measured.write(meas, d)
    synth.seal(truth, d)
    return d


def _copy_with(mset: Path, dest: Path, **cols) -> Path:
    import shutil

    shutil.copytree(mset, dest)
    df = pd.read_csv(dest / "measured.csv")
    for k, v in cols.items():
        df[k] = v
    df.to_csv(dest / "measured.csv", index=False)
    return dest


# ----------------------------------------------------------------------------- paths
def test_expand_confines_names_to_the_folder(tmp_path):
    base = tmp_path / "data"
    base.mkdir()
    (base / "a.png").write_bytes(b"x")
    (tmp_path / "decoy.png").write_bytes(b"x")
    (base / "link.png").symlink_to(tmp_path / "decoy.png")
    assert expand("a.png", base) == [str(base / "a.png")]
    for spec in (str(tmp_path / "decoy.png"), "../decoy.png", "/etc/*", "link.png", "*.png", "sub/../../decoy.png"):
        with pytest.raises(UserError, match="--allow-outside") as ei:
            expand(spec, base, param="measured")
        assert ei.value.param == "measured" and "\n" not in str(ei.value)
    assert expand("../decoy.png", base, allow_outside=True) == [str(base / "../decoy.png")]
    assert expand(str(tmp_path / "decoy.png")) == [str(tmp_path / "decoy.png")]  # the command line: no fence
    with pytest.raises(UserError) as ei:
        expand("nothing*.png", base, param="background")
    assert ei.value.param == "background"


def test_measured_npy_outside_the_folder_is_refused(mset, tmp_path):
    np.save(tmp_path / "decoy.npy", np.zeros((100, 100)))
    for i, ref in enumerate((str(tmp_path / "decoy.npy"), "../decoy.npy")):
        d = _copy_with(mset, tmp_path / f"M{i}", difference=ref)
        with pytest.raises(UserError, match="--allow-outside"):
            measured.load(d)
        m = measured.load(d, allow_outside=True)
        assert m.difference[0].shape == (100, 100) and not m.difference[0].any()


def test_measured_frames_outside_the_folder_are_refused(mset, tmp_path):
    d = _copy_with(mset, tmp_path / "M", images="/etc/*", background="/etc/*")
    with pytest.raises(UserError, match="--allow-outside") as ei:
        measured.load(d)
    assert ei.value.param == "measured" and "images" in ei.value.message


def test_camera_csv_outside_its_folder_is_refused(tmp_path):
    ph = read_phantoms()
    (tmp_path / "c").mkdir()
    rows = ["name,images,background"] + [f"{n},/etc/*,/etc/*" for n in ph["name"]]
    (tmp_path / "c" / "camera.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(UserError, match="--allow-outside") as ei:
        C.camera_features_from_csv(tmp_path / "c" / "camera.csv", ph)
    assert ei.value.param == "camera-csv"


def test_ids_that_are_not_file_names_are_refused_before_work(mset, tmp_path):
    d = tmp_path / "M"
    import shutil

    shutil.copytree(mset, d)
    df = pd.read_csv(d / "measured.csv")
    df.loc[0, "id"] = "a/../../x"
    df.to_csv(d / "measured.csv", index=False)
    with pytest.raises(UserError, match="file name"):
        measured.load(d)
    called = []

    class Sim:
        mesh, backend = "tiny", "toy"

        def run(self, plist):
            called.append(plist)
            raise AssertionError("solved before the ids were checked")

    with pytest.raises(UserError, match="file name"):
        synth.synthesize(synth.phantom_design(4, 0), [], Sim(), frames=2, ids=["a", "b/c", "d", "e"])
    for kw in ({"seed": -1}, {"frames": 10**20}, {"noise_scale": 1e308}, {"force_noise": float("inf")}):
        with pytest.raises(UserError):
            synth.synthesize(synth.phantom_design(4, 0), [], Sim(), **{"frames": 2, **kw})
    assert not called


# ----------------------------------------------------------------------------- damaged inputs
def _png_header(path: Path, w: int, h: int) -> None:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)))


def test_huge_png_header_is_refused_without_decoding(tmp_path):
    p = tmp_path / "big.png"
    _png_header(p, 100000, 100000)
    with pytest.raises(UserError) as ei:
        read_frame(p, param="images")
    assert ei.value.param == "images"
    _png_header(p, 9000, 9000)  # under Pillow's own limit, over a frame's
    with pytest.raises(UserError, match="more than"):
        read_frame(p, param="images")
    with pytest.raises(UserError, match="wrong size"):
        read_frame(p, (40, 40), param="images")
    _png_header(p, 60, 50)  # a plain wrong size is said as such, not as a corrupt file
    with pytest.raises(UserError, match="wrong size 60x50"):
        read_frame(p, (40, 40), param="images")


def test_damaged_calibration_files_are_refused(tmp_path):
    ph = read_phantoms()
    fem = np.abs(np.random.default_rng(0).normal(1, 0.2, (len(ph), 3))) + np.arange(len(ph))[:, None]
    cal = C.fit_calibration(ph, 2 * fem + 1, fem, {})
    good = tmp_path / "cal.json"
    cal.save(good)
    assert C.Calibration.load(good).fits["O1"].slope == pytest.approx(cal.fits["O1"].slope)
    doc = json.loads(good.read_text())
    damaged = {
        "nan slope": lambda d: d["fits"]["O1"].update(slope=float("nan")),
        "string intercept": lambda d: d["fits"]["O2"].update(intercept="1"),
        "settings list": lambda d: d.update(feature_settings=[1, 2]),
        "sensor string": lambda d: d.update(sensor="x"),
        "phantoms not a list": lambda d: d.update(phantoms=3),
    }
    for name, edit in damaged.items():
        d = json.loads(json.dumps(doc))
        edit(d)
        p = tmp_path / f"{name.replace(' ', '_')}.json"
        p.write_text(json.dumps(d))
        with pytest.raises(UserError) as ei:
            C.Calibration.load(p)
        assert ei.value.param == "calibration" and "\n" not in str(ei.value), name


def test_tables_with_repeated_columns_or_nothing_are_refused(tmp_path):
    ph = read_phantoms()
    rows = ["name,O1,O2,O3,O3"] + [f"{n},1,2,3,4" for n in ph["name"]]
    (tmp_path / "dup.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(UserError, match="more than once"):
        C.fem_features_from_csv(tmp_path / "dup.csv", ph)
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(UserError, match="not a readable CSV"):
        C.fem_features_from_csv(tmp_path / "empty.csv", ph)
    rows = ["name,O1,O2,O3"] + [f"{n},1,x,3" for n in ph["name"]]
    (tmp_path / "text.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(UserError, match="finite numbers"):
        C.fem_features_from_csv(tmp_path / "text.csv", ph)
    (tmp_path / "ph.csv").write_text("name,d,h,E\na,5,8,inf\nb,5,8,40\nc,6,8,40\n")
    with pytest.raises(UserError, match="positive numbers"):
        read_phantoms(tmp_path / "ph.csv")


def test_gap_synth_overwrite_keeps_files_it_did_not_write(mset, tmp_path):
    import shutil

    d = tmp_path / "M"
    shutil.copytree(mset, d)
    (d / "my_notes.txt").write_text("mine")
    with pytest.raises(UserError, match="my_notes.txt"):
        synth.check_out(d, overwrite=True)
    (d / "my_notes.txt").unlink()
    synth.check_out(d, overwrite=True)

"""Dataset landing/reading/compaction and the `dataset` CLI (no solver, no dask)."""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from elastimap.dataset import io
from elastimap.dataset.cli import main as dataset_main
from elastimap.dataset.schema import COLUMNS, SCHEMA_KEY
from elastimap.errors import UserError

SHAPE = (4, 4)


def _row(sid, status="ok", tag="design", d=8.0, h=7.0, E=50.0, o1=0.01):
    ok = status == "ok"
    nan = float("nan")
    return {
        "sample_id": sid,
        "tag": tag,
        "d": d,
        "h": h,
        "E": E,
        "O1": o1 if ok else nan,
        "O2": 0.1 if ok else nan,
        "O3": 10.0 if ok else nan,
        "force": 100.0 if ok else nan,
        "force_ref": 99.0 if ok else nan,
        "image": np.full(SHAPE, o1, dtype=np.float32) if ok else None,
        "params_json": "{}",
        "status": status,
        "error": "" if ok else "SolverError: boom",
        "ndofs": 10 if ok else None,
        "newton_iterations": 1 if ok else None,
        "seconds": 1.5,
        "peak_memory_mb": 50.0,
        "code_version": "test",
        "host": "h",
    }


def _land(tmp, rows, shape=SHAPE):
    ok = any(r["status"] == "ok" for r in rows)
    return io.land_rows(tmp, rows, shape if ok else None, 0.5 if ok else None)


def test_roundtrip_metadata_and_columns(tmp_path):
    _land(tmp_path, [_row("a", d=5), _row("b", d=6)])
    _land(tmp_path, [_row("c", status="failed")])
    df = io.read_samples(tmp_path)
    assert list(df["sample_id"]) == ["a", "b"]
    assert list(df.columns) == list(COLUMNS)
    assert io.read_image_meta(tmp_path) == (SHAPE, 0.5)
    imgs = io.stack_images(df, SHAPE)
    assert imgs.shape == (2, 4, 4) and imgs.dtype == np.float32
    assert len(io.read_samples(tmp_path, status=None)) == 3
    assert list(io.read_samples(tmp_path, status="failed")["sample_id"]) == ["c"]
    sub = io.read_samples(tmp_path, columns=["d", "O1"])
    assert list(sub.columns) == ["d", "O1"] and list(sub["d"]) == [5.0, 6.0]
    meta = json.loads(pq.read_schema(next(tmp_path.glob("*.parquet"))).metadata[SCHEMA_KEY.encode()])
    assert meta["version"] == 1 and meta["units"]["E"] == "kPa"
    assert io.landed_status(tmp_path) == {"a": "ok", "b": "ok", "c": "failed"}
    with pytest.raises(UserError, match="unknown column"):
        io.read_samples(tmp_path, columns=["nope"])


def test_dedupe_ok_beats_failed_then_newest(tmp_path):
    _land(tmp_path, [_row("a", status="failed")])
    time.sleep(0.01)
    _land(tmp_path, [_row("a", o1=0.02)])
    time.sleep(0.01)
    _land(tmp_path, [_row("a", status="failed")])  # a later failure never hides an ok row
    _land(tmp_path, [_row("b", status="failed")])
    time.sleep(0.01)
    r = _row("b", status="failed")
    r["error"] = "newest"
    _land(tmp_path, [r])
    df = io.read_samples(tmp_path, status=None)
    assert len(df) == 2
    assert df.set_index("sample_id").loc["a", "O1"] == pytest.approx(0.02)
    assert df.set_index("sample_id").loc["b", "error"] == "newest"


def test_compact_merges_drops_superseded_keeps_metadata(tmp_path):
    for i in range(7):
        _land(tmp_path, [_row(f"s{i}", d=2.0 + i)])
    _land(tmp_path, [_row("s0", status="failed")])
    (tmp_path / ".b-junk.parquet.123.tmp").write_bytes(b"half")  # a killed writer's leftover
    before = io.read_samples(tmp_path, status=None)
    r = io.compact(tmp_path, batch_rows=3)
    assert r == {"files_before": 8, "files_after": 3, "rows": 7, "dropped": 1}
    after = io.read_samples(tmp_path, status=None)
    pd.testing.assert_frame_equal(after.drop(columns=["image"]), before.drop(columns=["image"]), check_dtype=False)
    assert io.read_image_meta(tmp_path) == (SHAPE, 0.5)
    assert all(f.name.startswith("b-") for f in tmp_path.glob("*.parquet"))
    assert io.remove_stale_tmp(tmp_path) == 1


def test_nonconforming_and_bad_paths(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        io.read_samples(tmp_path / "missing")
    with pytest.raises(UserError, match="no Parquet files"):
        io.read_samples(tmp_path)
    pq.write_table(pa.table({"x": [1]}), tmp_path / "foreign.parquet")
    with pytest.raises(UserError, match="not an elastimap sample file"):
        io.read_samples(tmp_path)
    (tmp_path / "foreign.parquet").write_bytes(b"not parquet at all")
    with pytest.raises(UserError, match="not a readable Parquet file"):
        io.read_samples(tmp_path / "foreign.parquet")


def test_image_geometry_mismatch_is_reported(tmp_path):
    _land(tmp_path, [_row("a")])
    r = _row("b")
    r["image"] = np.zeros((2, 2), np.float32)
    io.land_rows(tmp_path, [r], (2, 2), 1.0)
    with pytest.raises(UserError, match="disagree on the elasticity-image geometry"):
        io.read_image_meta(tmp_path)


def _cli(args, capsys):
    with pytest.raises(SystemExit) as e:
        dataset_main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def test_cli_inspect_export_compact_plot(tmp_path, capsys):
    ds = tmp_path / "ds"
    ds.mkdir()
    rng = np.random.default_rng(1)
    for i in range(6):
        _land(
            ds,
            [
                _row(
                    f"s{i}",
                    d=rng.uniform(2, 15),
                    h=rng.uniform(5, 8),
                    E=rng.uniform(10, 200),
                    o1=rng.uniform(0, 0.03),
                    tag="phantom:size-1" if i == 0 else "design",
                )
            ],
        )
    _land(ds, [_row("bad", status="failed")])
    code, out, err = _cli(["inspect", str(ds)], capsys)
    assert code == 0, err
    assert "status: failed 1, ok 6" in out and "SolverError: boom" in out and "NaN/inf in ok rows: none" in out
    code, out, _ = _cli(["inspect", str(ds), "--json"], capsys)
    assert json.loads(out)["status"] == {"ok": 6, "failed": 1}
    code, out, _ = _cli(["export", str(ds), "--out", str(tmp_path / "t.csv")], capsys)
    assert code == 0 and (tmp_path / "t.csv").read_text().count("\n") == 8
    code, out, _ = _cli(["compact", str(ds)], capsys)
    assert code == 0 and "7 files -> 1" in out
    code, out, err = _cli(["plot", str(ds), "--out", str(tmp_path / "figs")], capsys)
    assert code == 0, err
    for name in ("scatter3d.png", "features_vs_params.png", "images.png"):
        f = tmp_path / "figs" / name
        assert f.stat().st_size > 10_000 and f.read_bytes()[:4] == b"\x89PNG"


def test_cli_bad_path_is_one_line(tmp_path, capsys):
    code, out, err = _cli(["inspect", str(tmp_path / "nope")], capsys)
    assert (
        code == 2 and err.strip().count("\n") == 0 and err.startswith("error: PATH:")
    )  # the argument, as --help names it
    (tmp_path / "x.parquet").write_bytes(b"junk")
    code, out, err = _cli(["inspect", str(tmp_path / "x.parquet")], capsys)
    assert code == 2 and "not a readable Parquet file" in err


def test_lock_live_holder_refused_stale_taken_over(tmp_path, capsys):
    import os
    import subprocess
    import sys

    _land(tmp_path, [_row("a")])
    lock = io.acquire_lock(tmp_path)
    code, _, err = _cli(["compact", str(tmp_path)], capsys)  # this very process holds it: live
    assert code == 2 and "being written by another sweep or compaction" in err
    lock.unlink()
    # a lock left by a process that is gone (kill -9) is taken over
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / io.LOCK).write_text(json.dumps({"pid": int(dead.stdout), "host": os.uname().nodename, "created": 1.0}))
    code, out, err = _cli(["compact", str(tmp_path)], capsys)
    assert code == 0, err
    assert not (tmp_path / io.LOCK).exists()


def test_lock_not_left_when_it_cannot_be_written(tmp_path, monkeypatch):
    """A full disk while the lock is written: one error line, no empty lock left behind (an empty,
    fresh lock would refuse the very rerun the error asks for)."""
    import errno

    from elastimap.errors import UserError

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(io.json, "dump", full)
        with pytest.raises(UserError, match="cannot write the lock .*No space left"):
            io.acquire_lock(tmp_path)
    assert not (tmp_path / io.LOCK).exists()
    io.acquire_lock(tmp_path).unlink()  # once space is back the lock is taken at once


def test_reader_survives_compaction_running_alongside(tmp_path):
    import threading

    for i in range(40):
        _land(tmp_path, [_row(f"s{i:02d}")])
    stop = threading.Event()
    errors = []

    def compactor():
        k = 0
        while not stop.is_set():
            try:
                for j in range(3):  # new single rows keep landing, then get merged
                    _land(tmp_path, [_row(f"s{j:02d}")])
                io.compact(tmp_path, batch_rows=7 + k % 5)
            except Exception as exc:  # noqa: BLE001
                errors.append(exc)
            k += 1

    t = threading.Thread(target=compactor)
    t.start()
    try:
        for _ in range(15):
            df = io.read_samples(tmp_path, columns=["sample_id", "O1"])
            assert len(df) == 40 and df["sample_id"].is_unique
    finally:
        stop.set()
        t.join()
    assert not errors

"""Sweep: design, input checks, fan-out, resume after SIGKILL, crash recording, benchmark.

The fast tests run the real command with the SYNTHETIC stand-in (hidden option
``--solver synthetic[:...]``, see :mod:`elastimap.solver.synthetic`); one end-to-end run and the
SIGKILL/resume test use real tiny-mesh solves.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from sweep_helpers import ROOT, run_sweep
from sweep_helpers import sweep_env as _env
from sweep_helpers import synthetic as _synthetic

from elastimap.dataset import io
from elastimap.dataset.phantoms import phantom_samples
from elastimap.errors import UserError
from elastimap.solver.params import depth_range
from elastimap.sweep import design as dsg
from elastimap.sweep.cli import main as sweep_main


def _sweep(args, env=None, timeout=240):
    return run_sweep(args, env=env, timeout=timeout)


def _cli(args, capsys):
    with pytest.raises(SystemExit) as e:
        sweep_main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


# ----------------------------------------------------------------------------- design


def test_design_points_valid_deterministic_and_spread():
    r = dsg.parse_ranges(None)
    assert r["E"].scale == "log" and r["h"].auto
    for design in ("lhs", "sobol"):
        pts = dsg.design_points(64, design, 3, r)
        assert pts == dsg.design_points(64, design, 3, r)
        assert len({p["sample_id"] for p in pts}) == 64
        for p in pts:
            lo, hi = depth_range(p["d"])
            assert 2 <= p["d"] <= 15 and lo <= p["h"] <= hi and 10 <= p["E"] <= 200
        logE = np.log([p["E"] for p in pts])
        assert np.histogram(logE, bins=4)[0].min() >= 10  # log-uniform: every quarter of log E filled
    # a Sobol sweep extended to more samples keeps the ids and points of the smaller one
    assert dsg.design_points(8, "sobol", 1, r) == dsg.design_points(16, "sobol", 1, r)[:8]
    assert dsg.design_points(8, "lhs", 1, r)[0]["sample_id"] != dsg.design_points(16, "lhs", 1, r)[0]["sample_id"]
    h = dsg.parse_ranges("h=3:9,E=20:40:lin")
    for p in dsg.design_points(32, "lhs", 0, h):
        lo, hi = depth_range(p["d"])
        assert max(3, lo) - 1e-9 <= p["h"] <= min(9, hi) + 1e-9 and 20 <= p["E"] <= 40


@pytest.mark.parametrize(
    "text, msg",
    [
        ("d=2", "expected LO:HI"),
        ("x=1:2", "unknown parameter"),
        ("d=5:2", "LO must be < HI"),
        ("E=0:10:log", "needs LO > 0"),
        ("d=2:18", "does not fit"),
        ("h=0.1:1", "no valid depth"),
        ("d=a:3", "not a number"),
        ("E=1:2:cubic", "lin or log"),
        ("d=2:3,d=2:4", "given twice"),
    ],
)
def test_bad_ranges(text, msg):
    with pytest.raises(UserError, match=msg):
        dsg.parse_ranges(text)


def test_samples_table_parquet_and_csv(tmp_path):
    import pandas as pd

    df = pd.DataFrame({"d": [5.0, 8.0], "h": [6.0, 9.0], "E": [50.0, 120.0], "sample_id": ["a", "b"]})
    df.to_parquet(tmp_path / "s.parquet")
    rows = dsg.load_samples(str(tmp_path / "s.parquet"))
    assert [(r["sample_id"], r["d"], r["E"], r["tag"]) for r in rows] == [
        ("a", 5.0, 50.0, "user"),
        ("b", 8.0, 120.0, "user"),
    ]
    (tmp_path / "s.csv").write_text("# comment\nd, h, E\n5,6,50\n")
    (r,) = dsg.load_samples(str(tmp_path / "s.csv"))
    assert r["sample_id"].startswith("user-") and r["h"] == 6.0
    assert dsg.load_samples(str(tmp_path / "s.csv"))[0]["sample_id"] == r["sample_id"]  # stable


def test_phantoms_file_nine_valid_inclusions():
    ph = phantom_samples()
    assert len(ph) == 9 and len({p["sample_id"] for p in ph}) == 9
    assert {p["tag"].split(":")[1].split("-")[0] for p in ph} == {"size", "depth", "hardness"}
    assert all(p["tissue_E"] == 5.0 and p["tissue_thickness"] == 20.0 for p in ph)


# ----------------------------------------------------------------------------- input errors: nothing written


@pytest.mark.parametrize(
    "args, msg",
    [
        (["--n", "-3"], "--n: must be an integer"),
        (["--jobs", "0"], "--jobs: must be an integer"),
        (["--ranges", "d=1:30"], "--ranges: d up to 30"),
        (["--mesh", "huge"], "--mesh: must be one of"),
        (["--samples", "/nonexistent.csv"], "--samples: /nonexistent.csv does not exist"),
        (["--n", "0"], "nothing to run"),
        (["--design", "grid"], "--design: must be one of"),
        (["--timeout", "-1"], "--timeout: must be >= 0"),
    ],
)
def test_invalid_options_clear_error_nothing_written(tmp_path, capsys, args, msg):
    out = tmp_path / "out"
    code, _, err = _cli(["run", "--out", str(out), *args], capsys)
    assert code == 2 and msg in err and err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize(
    "content, msg",
    [
        ("d,h\n5,6\n", "lacks column(s) E"),
        ("d,h,E,colour\n5,6,50,red\n", "unknown column(s) colour"),
        ("d,h,E\n5,6,50\n5,,50\n", "row 2: h is missing"),
        ("d,h,E\n5,6,50\n8,15,50\n", "is not a valid solve: h: centre depth must be in"),
        ("d,h,E\n5,6,50\n5,6,50\n", "duplicate sample id"),
        ("d,h,E\n5,6,-1\n", "E: must be > 0 kPa"),
    ],
)
def test_bad_sample_tables(tmp_path, capsys, content, msg):
    f = tmp_path / "s.csv"
    f.write_text(content)
    out = tmp_path / "out"
    code, _, err = _cli(["run", "--samples", str(f), "--out", str(out)], capsys)
    assert code == 2 and msg in err, err
    assert not out.exists()


def test_foreign_nonempty_out_dir_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, _, err = _cli(["run", "--n", "2", "--mesh", "tiny", "--out", str(out)], capsys)
    assert code == 2 and "holds no sweep manifest" in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_unreadable_samples_file(tmp_path, capsys):
    f = tmp_path / "s.parquet"
    f.write_bytes(b"garbage")
    code, _, err = _cli(["run", "--samples", str(f), "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and "cannot be read" in err
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- runs (fake solver)


def test_synthetic_sweep_phantoms_user_rows_and_resume(tmp_path):
    table = tmp_path / "t.csv"
    table.write_text("sample_id,d,h,E\nmine-1,6,7,40\n")
    out = tmp_path / "ds"
    args = [
        "run",
        *_synthetic(),
        "--n",
        "6",
        "--jobs",
        "2",
        "--mesh",
        "tiny",
        "--phantoms",
        "--samples",
        str(table),
        "--out",
        str(out),
        "--seed",
        "4",
    ]
    r = _sweep(args)
    assert r.returncode == 0, r.stderr
    assert "16 done this run (ok 16, failed 0), 0 skipped" in r.stdout and "samples/min" in r.stdout
    df = io.read_samples(out)
    assert len(df) == 16 and df["sample_id"].is_unique
    assert sorted(set(df["tag"]))[:2] == ["design", "phantom:depth-1"] and "user" in set(df["tag"])
    assert set(df.loc[df.tag == "user", "sample_id"]) == {"mine-1"}
    assert io.read_image_meta(out) == ((50, 50), 0.5)
    assert set(df["solver"]) == {"synthetic"} and df["key"].str.len().eq(64).all()  # labelled, keyed
    assert [f.name[:2] for f in out.glob("*.parquet")] == ["b-"]  # compacted at the end
    import pyarrow.dataset as pads  # plain pyarrow readers (training) see the same rows, manifest skipped

    assert pads.dataset(out, format="parquet").to_table(columns=["sample_id"]).num_rows == 16
    r = _sweep(args)
    assert r.returncode == 0 and "0 done this run" in r.stdout and "16 skipped" in r.stdout
    # other solver settings into the same directory are refused
    r = _sweep([*args[:-4], "--mesh", "coarse", "--out", str(out)])
    assert r.returncode == 2 and "other solver settings" in r.stderr
    # so is the forward model resuming a folder of SYNTHETIC rows
    r = _sweep([a for a in args if a not in _synthetic()])
    assert r.returncode == 2 and "by the 'synthetic' solver" in r.stderr, r.stderr
    # a reused id with other parameters (edited table) is refused, not silently kept
    table.write_text("sample_id,d,h,E\nmine-1,6,7,41\n")
    r = _sweep(args)
    assert r.returncode == 2 and "mine-1 (landed d=6, h=7, E=40; now d=6, h=7, E=41)" in r.stderr, r.stderr


def test_crash_recorded_failed_others_land_then_retry(tmp_path):
    table = tmp_path / "t.csv"
    # more samples than workers: with dask's default worker-saturation a queued bystander on the
    # dying worker was blamed for the crash too (KilledWorker without ever running)
    table.write_text("d,h,E\n5,6,50\n6,7,60\n7.5,8,70\n8,8,80\n4,5,40\n9,9,90\n10,9,100\n3,5,30\n")
    out = tmp_path / "ds"
    log = tmp_path / "starts.log"
    args = ["run", "--samples", str(table), "--jobs", "2", "--mesh", "tiny", "--out", str(out)]
    r = _sweep([*args, *_synthetic(crash_d=7.5, fail_d=4, log=log, seconds=0.1)])
    assert r.returncode == 0, r.stderr
    df = io.read_samples(out, status=None).set_index("d")
    assert (df["status"] == "ok").sum() == 6, df[["status", "error"]]
    assert df.loc[7.5, "status"] == "failed" and "worker crashed" in df.loc[7.5, "error"]
    assert df.loc[4.0, "status"] == "failed" and "SyntheticSolverError" in df.loc[4.0, "error"]
    starts = [ln.split()[0] for ln in log.read_text().splitlines()]
    assert starts.count("7.5") == 2  # allowed-failures: one retry, then recorded
    # --retry-failed reruns only the failures; now they succeed
    r = _sweep([*args, *_synthetic(), "--retry-failed"])
    assert r.returncode == 0 and "2 done this run (ok 2, failed 0), 6 skipped" in r.stdout, r.stdout + r.stderr
    df = io.read_samples(out, status=None)
    assert len(df) == 8 and (df["status"] == "ok").all()


def test_hung_sample_times_out_once_others_land(tmp_path):
    table = tmp_path / "t.csv"
    table.write_text("d,h,E\n5,6,50\n6,7,60\n7,8,70\n")
    out = tmp_path / "ds"
    log = tmp_path / "starts.log"
    r = _sweep(
        [
            "run",
            "--samples",
            str(table),
            "--jobs",
            "2",
            "--mesh",
            "tiny",
            "--out",
            str(out),
            "--timeout",
            "3",
            *_synthetic(hang_d=6, log=log, seconds=0.1),
        ]
    )
    assert r.returncode == 0, r.stderr
    df = io.read_samples(out, status=None).set_index("d")
    assert list(df["status"]) == ["ok", "failed", "ok"]
    assert df.loc[6.0, "error"].startswith("Timeout: no result after 3 s")
    assert [ln.split()[0] for ln in log.read_text().splitlines()].count("6") == 1  # the retry did not hang again


def test_bench_command_small(tmp_path):
    r = _sweep(["bench", *_synthetic(), "--n", "4", "--mesh", "tiny", "--out", str(tmp_path / "b")])
    assert r.returncode == 0, r.stderr
    assert "speed-up jobs 2 vs 1" in r.stdout and "driver CPU ms/sample" in r.stdout
    for k in (1, 2):
        assert len(io.read_samples(tmp_path / "b" / f"jobs{k}")) == 4


# ----------------------------------------------------------------------------- real tiny solves


def _wait_rows(out: Path, k: int, proc, timeout=120) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if len(list(out.glob("r-*.parquet"))) >= k:
            return
        if proc.poll() is not None:
            raise AssertionError(f"sweep ended early: {proc.stderr.read() if proc.stderr else ''}")
        time.sleep(0.2)
    raise AssertionError("no rows landed in time")


def test_sigkill_driver_then_rerun_exactly_n_ok_real_solves(tmp_path):
    n = 10
    out = tmp_path / "ds"
    args = ["run", "--n", str(n), "--jobs", "2", "--mesh", "tiny", "--out", str(out), "--no-progress"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "elastimap.sweep.cli", *args],
        env=_env(),
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        _wait_rows(out, 2, proc)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    landed = io.landed_status(out)
    assert 2 <= len(landed) < n, landed
    assert (out / ".sweep.lock").exists()  # left behind by the killed driver; the rerun takes it over
    r = _sweep(args, _env())
    assert r.returncode == 0, r.stderr
    assert f"{len(landed)} skipped" in r.stdout
    df = io.read_samples(out, status=None)
    assert len(df) == n and df["sample_id"].is_unique and (df["status"] == "ok").all()
    assert (df["ndofs"] > 0).all() and io.read_image_meta(out)[0] == (50, 50)
    assert np.isfinite(df[["O1", "O2", "O3", "force"]].to_numpy()).all()


def test_external_scheduler_real_solves(tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        out = tmp_path / "ds"
        r = _sweep(
            ["run", "--n", "3", "--mesh", "tiny", "--out", str(out), "--scheduler", cluster.scheduler_address], _env()
        )
    assert r.returncode == 0, r.stderr
    df = io.read_samples(out)
    assert len(df) == 3 and (df["ndofs"] > 0).all()


def test_moduli_per_mesh_design():
    """``--moduli-per-mesh k``: n/k geometries, each with k moduli, one in each stratum of log E."""
    r = dsg.parse_ranges(None)
    pts = dsg.design_points(64, "lhs", 3, r, moduli_per_mesh=8)
    assert pts == dsg.design_points(64, "lhs", 3, r, moduli_per_mesh=8)
    assert len({p["sample_id"] for p in pts}) == 64
    assert not {p["sample_id"] for p in pts} & {p["sample_id"] for p in dsg.design_points(64, "lhs", 3, r)}
    lo, hi = np.log(10.0), np.log(200.0)
    for g in range(8):
        grp = pts[8 * g : 8 * g + 8]
        assert len({(p["d"], p["h"]) for p in grp}) == 1  # one geometry
        strata = np.floor(8 * (np.log([p["E"] for p in grp]) - lo) / (hi - lo)).astype(int)
        assert sorted(strata) == list(range(8))  # one modulus in each eighth of log E
    assert len({(p["d"], p["h"]) for p in pts}) == 8
    odd = dsg.design_points(60, "lhs", 3, r, moduli_per_mesh=8)  # 7 geometries of 8, the last of 4
    assert len(odd) == 60 and len({(p["d"], p["h"]) for p in odd}) == 8
    last = np.log([p["E"] for p in odd[56:]])
    assert sorted(np.floor(4 * (last - lo) / (hi - lo)).astype(int)) == [0, 1, 2, 3]
    with pytest.raises(UserError, match="moduli-per-mesh"):
        dsg.design_points(64, "lhs", 3, r, moduli_per_mesh=0)


def test_moduli_per_mesh_sweep_shares_a_mesh_and_gives_each_samples_solve(tmp_path):
    """A sweep with --moduli-per-mesh runs each geometry's samples as one task on one mesh; every
    row holds what a single ``solve`` of its sample gives (tiny mesh, real solves)."""
    from elastimap.solver.api import solve
    from elastimap.solver.params import Discretisation, SolveParams

    out = tmp_path / "ds"
    args = ["run", "--n", "8", "--moduli-per-mesh", "4", "--mesh", "tiny", "--jobs", "2", "--out", str(out)]
    r = _sweep([*args, "--no-progress"], _env())
    assert r.returncode == 0, r.stderr
    df = io.read_samples(out, status=None).sort_values("sample_id")
    assert len(df) == 8 and (df["status"] == "ok").all() and df[["d", "h"]].drop_duplicates().shape[0] == 2
    for _, row in df.iloc[[0, 3, 5]].iterrows():
        want = solve(SolveParams(disc=Discretisation(mesh="tiny")).with_inclusion(d=row.d, h=row.h, E=row.E))
        for k in ("O1", "O2", "O3", "force"):
            assert row[k] == pytest.approx(getattr(want, k), rel=1e-9, abs=1e-12), k
    again = _sweep([*args, "--no-progress"], _env())  # resumes: nothing left to run
    assert again.returncode == 0 and "8 skipped" in again.stdout
    other = _sweep(["run", "--n", "8", "--mesh", "tiny", "--out", str(out), "--no-progress"], _env())
    assert other.returncode == 2 and "--moduli-per-mesh" in other.stderr  # another design: refused, names it


def test_a_worker_dying_inside_a_geometrys_task_loses_only_that_sample(tmp_path):
    """A task of several samples (one geometry) whose worker dies at its third sample: the two
    landed before stay landed once, the crashing one is recorded failed after its retry, the one
    after it runs again alone and lands."""
    table = tmp_path / "t.csv"
    table.write_text("d,h,E\n5,6,20\n5,6,40\n5,6,60\n5,6,80\n7,8,30\n7,8,50\n")
    out = tmp_path / "ds"
    log = tmp_path / "starts.log"
    args = ["run", "--samples", str(table), "--jobs", "2", "--mesh", "tiny", "--out", str(out)]
    r = _sweep([*args, *_synthetic(crash_E=60, log=log, seconds=0.1)])
    assert r.returncode == 0, r.stderr
    df = io.read_samples(out, status=None)
    assert len(df) == 6 and df["sample_id"].is_unique
    df = df.set_index("E")
    assert df.loc[60.0, "status"] == "failed" and "worker crashed" in df.loc[60.0, "error"]
    assert (df.drop(index=60.0)["status"] == "ok").all(), df[["status", "error"]]
    starts = [float(ln.split()[2]) for ln in log.read_text().splitlines()]
    assert starts.count(60.0) == 2 and starts.count(80.0) == 1  # the task's retry, then 80 alone

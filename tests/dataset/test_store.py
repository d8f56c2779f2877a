"""The solve store (elastimap.dataset.store): keys, round trip, kill -9 safety, and the sweep,
gap and identify reading through it.  Results come from the SYNTHETIC stand-in
(elastimap.solver.synthetic, not physics): these tests check storage, not solves."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from elastimap.dataset import io
from elastimap.dataset.store import SolveStore, canonical_json, params_key
from elastimap.solver import synthetic
from elastimap.solver.params import Discretisation, SolveParams

ROOT = Path(__file__).resolve().parents[2]


def _p(d=8.0, h=7.0, E=50.0, **disc) -> SolveParams:
    return SolveParams(disc=Discretisation(mesh="tiny", **disc)).with_inclusion(d=d, h=h, E=E)


# ----------------------------------------------------------------------------- key


def test_key_is_sha256_of_canonical_params_and_normalises_numbers():
    p = _p()
    assert len(params_key(p)) == 64 and params_key(p) == params_key(_p())
    assert json.loads(canonical_json(p)) == json.loads(json.dumps(p.to_dict()))  # nothing but to_dict
    assert params_key(_p(d=8)) == params_key(_p(d=8.0))  # int and float: one key
    assert params_key(p.with_inclusion(offset_x=-0.0)) == params_key(p)  # -0.0 is 0.0
    # an effect switch at its default is left out of to_dict: the key of a plain solve stays put
    assert params_key(p.replace(disc=dataclasses.replace(p.disc, friction_kt=0.0))) == params_key(p)


def test_different_params_give_different_keys():
    p = _p()
    variants = [
        p,
        p.with_inclusion(d=8.000001),
        p.with_inclusion(h=7.5),
        p.with_inclusion(E=51.0),
        p.replace(tissue=dataclasses.replace(p.tissue, nonlinearity=0.5)),
        p.replace(disc=dataclasses.replace(p.disc, mesh="coarse")),
        p.replace(disc=dataclasses.replace(p.disc, friction_kt=0.3)),
        p.replace(probe=dataclasses.replace(p.probe, layers=((2.0, 300.0), (3.0, 150.0), (5.0, 60.0)))),
        p.replace(loading=dataclasses.replace(p.loading, force=100.0)),
    ]
    assert len({params_key(v) for v in variants}) == len(variants)


def test_key_same_in_another_process():
    p = _p(d=6.25, h=5.5, E=123.4)
    code = (
        "from elastimap.dataset.store import params_key\n"
        "from elastimap.solver.params import SolveParams, Discretisation\n"
        "p = SolveParams(disc=Discretisation(mesh='tiny')).with_inclusion(d=6.25, h=5.5, E=123.4)\n"
        "print(params_key(p))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONHASHSEED": "123"},
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == params_key(p)


# ----------------------------------------------------------------------------- round trip


def test_put_get_round_trip_and_labels(tmp_path):
    st = SolveStore(tmp_path / "s", solver="synthetic")
    p = _p()
    assert st.get(p) is None and p not in st and len(st) == 0
    res = synthetic.solve(p)
    key = st.put(p, res)
    assert key == params_key(p)
    got = SolveStore(tmp_path / "s", solver="synthetic").get(p, need_raw=True)  # a fresh reader
    assert got.params == p and (got.O1, got.O2, got.O3, got.force, got.force_ref, got.delta) == (
        res.O1,
        res.O2,
        res.O3,
        res.force,
        res.force_ref,
        res.delta,
    )
    assert got.image.dtype == np.float32 and np.array_equal(got.image, res.image.astype(np.float32))
    assert np.array_equal(got.image_raw, res.image_raw.astype(np.float32)) and got.pixel == res.pixel
    assert st.get(p.with_inclusion(E=51.0)) is None
    assert SolveStore(tmp_path / "s").get(p) is None  # SYNTHETIC rows never answer for the FEM
    # the newest row of a key wins
    later = dataclasses.replace(res, O1=res.O1 * 2)
    st.put(p, later)
    assert st.get(p).O1 == later.O1 and len(st) == 1
    # solve(): get or solve + put, returned as stored
    calls = []

    def counting(q):
        calls.append(q)
        return synthetic.solve(q)

    counting.solver_name = "synthetic"
    q = _p(d=5.0, h=6.0)
    a = st.solve(q, counting)
    b = st.solve(q, counting)
    assert len(calls) == 1 and np.array_equal(a.image, b.image) and a.image.dtype == np.float32


def test_get_many_reads_each_file_once_and_skips_failed(tmp_path):
    st = SolveStore(tmp_path, solver="synthetic")
    ps = [_p(d=d) for d in (4.0, 5.0, 6.0)]
    st.put_many([(p, synthetic.solve(p)) for p in ps])
    bad = dataclasses.replace(synthetic.solve(_p(d=7.0)), O2=float("nan"))
    st.put(_p(d=7.0), bad)  # lands as a failed row: never served
    got = st.get_many([ps[2], _p(d=7.0), ps[0], _p(d=9.0)])
    assert [g is not None for g in got] == [True, False, True, False]
    assert got[0].params.inclusion.d == 6.0 and got[2].params.inclusion.d == 4.0
    assert len(list(tmp_path.glob("*.parquet"))) == 2


def test_old_rows_without_key_still_read_and_compact(tmp_path):
    """A sweep folder from before the key (no key/solver/delta/image_raw columns) serves as a store."""
    p = _p(d=6.0)
    row = {
        k: v
        for k, v in __import__("elastimap.sweep.jobs", fromlist=["x"])
        .result_row({"sample_id": "old-1", "d": 6.0, "h": 7.0, "E": 50.0}, p, synthetic.solve(p), 0.1)
        .items()
    }
    t = io.to_table([row], (50, 50), 0.5).drop_columns(["key", "solver", "delta", "image_raw"])
    io.write_atomic(t, tmp_path / io.new_name("b"))
    got = SolveStore(tmp_path).get(p)  # no solver column: counted as 'fem'
    assert got is not None and got.delta == p.loading.delta and got.image_raw is None
    assert np.array_equal(got.image.ravel(), row["image"])
    q = _p(d=5.0)
    SolveStore(tmp_path).put(q, synthetic.solve(q))
    info = io.compact(tmp_path)  # old and new files merge (missing columns become nulls)
    assert info["rows"] == 2 and info["files_after"] == 1
    assert SolveStore(tmp_path).get(p) is not None and SolveStore(tmp_path).get(q, need_raw=True) is not None


def test_legacy_gap_parts_are_not_read(tmp_path):
    (tmp_path / "solves-123-abc.parquet").write_bytes(b"not ours")
    st = SolveStore(tmp_path)
    assert st.get(_p()) is None and len(st) == 0


# ----------------------------------------------------------------------------- kill -9

_WRITER = """
import sys
from elastimap.dataset.store import SolveStore
from elastimap.solver import synthetic
from elastimap.solver.params import SolveParams, Discretisation
st = SolveStore(sys.argv[1], solver="synthetic")
i = 0
while True:
    p = SolveParams(disc=Discretisation(mesh="tiny")).with_inclusion(d=4.0 + 1e-3 * i, h=7.0, E=50.0)
    st.put(p, synthetic.solve(p))
    i += 1
    if i == 20:
        print("ready", flush=True)
"""


def test_kill_9_while_putting_leaves_a_readable_store(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.3)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    st = SolveStore(tmp_path, solver="synthetic")
    n = len(st)
    assert n >= 20
    ps = [_p(d=4.0 + 1e-3 * i) for i in range(n)]
    got = st.get_many(ps, need_raw=True)
    assert all(g is not None and np.isfinite(g.image).all() for g in got)
    assert all(not f.name.startswith(".") for f in tmp_path.glob("*.parquet"))  # temporaries stay hidden


# ----------------------------------------------------------------------------- the three users


def test_sweep_folder_serves_as_a_store(tmp_path):
    from elastimap.sweep import jobs

    base = _p().to_dict()
    sample = {"sample_id": "s-1", "tag": "design", "d": 6.0, "h": 6.5, "E": 80.0}
    r = jobs.run_sample(sample, base, str(tmp_path), solver=synthetic.solve)
    assert r["status"] == "ok"
    df = io.read_samples(tmp_path)
    p = jobs.sample_params(sample, SolveParams.from_dict(base))
    assert df["key"].tolist() == [params_key(p)] and df["solver"].tolist() == ["synthetic"]
    got = SolveStore(tmp_path, solver="synthetic").get(p)
    assert got is not None and got.O1 == df["O1"][0] and np.array_equal(got.image.ravel(), df["image"][0])
    assert got.image_raw is None and SolveStore(tmp_path, solver="synthetic").get(p, need_raw=True) is None


def test_identify_cached_solve_reads_through_the_store(tmp_path):
    from elastimap.workflows.solves import cached_solve, params_of

    a = cached_solve(8.0, 7.0, 60.0, mesh="tiny", cache=str(tmp_path), solver=synthetic.solve)
    files = sorted(tmp_path.glob("*.parquet"))
    b = cached_solve(8.0, 7.0, 60.0, mesh="tiny", cache=str(tmp_path), solver=synthetic.solve)
    assert sorted(tmp_path.glob("*.parquet")) == files and len(files) == 1  # served, not solved again
    assert set(a) == {"image", "image_raw", "O", "force", "force_ref", "theta", "delta", "seconds"}
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert a["image"].dtype == np.float64 and a["image"].shape == (50, 50)
    # another sizing is another discretisation: solved and kept apart, the fixed one still served
    cached_solve(8.0, 7.0, 60.0, mesh="tiny", cache=str(tmp_path), solver=synthetic.solve, sizing="by_d")
    assert len(sorted(tmp_path.glob("*.parquet"))) == 2
    assert params_of(8.0, 7.0, 60.0, "tiny", 3.0, 0.0, sizing="by_d").disc.sizing == "by_d"
    b2 = cached_solve(8.0, 7.0, 60.0, mesh="tiny", cache=str(tmp_path), solver=synthetic.solve)
    assert np.array_equal(b2["image"], a["image"]) and len(sorted(tmp_path.glob("*.parquet"))) == 2
    p = params_of(8.0, 7.0, 60.0, "tiny", 3.0, 0.0)
    assert np.array_equal(SolveStore(tmp_path, solver="synthetic").get(p).image, a["image"].astype(np.float32))

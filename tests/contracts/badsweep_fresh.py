#!/usr/bin/env python
"""A fresh bad-input sweep of the ``elastimap`` command line (issue 40's goal).

Written by a session that did not make the fixes, without reading the earlier sweeps
(``robust_badsweep.py``, ``test_bad_inputs.py``, ``test_robust_*.py``) or docs/errors.md.
Not collected by pytest (no ``test_`` prefix); run it as::

    .venv/bin/python tests/contracts/badsweep_fresh.py [--only PATTERN] [--keep]

Every case runs ``elastimap ...`` in a fresh copy of a small fixture set (tiny mesh, tiny sizes),
one process at a time, and states what a clean answer is:

* ``refuse``: exit code 2, exactly one non-empty stderr line that names the flag or file,
  no traceback, nothing written anywhere under the case's folder (a snapshot of every file,
  its size and hash, before and after);
* ``ok``: exit code 0, no traceback, and the case's own check of the output;
* ``either``: a valid edge input that may be answered either way, but cleanly.

Then the fault scenarios: SIGTERM / SIGINT / kill -9 of ``sweep run`` with the real solver on
the tiny mesh (nothing lost, duplicated or mixed on resume), full disks (a small tmpfs, filled),
read-only targets (a read-only tmpfs; the sweep runs as root, so chmod proves nothing) and a
killed ``gap diagnose``.  The mounts need root; without it those scenarios are reported skipped.

It prints per-command counts, the clean percentage, the traceback count and each failing case on
one line.  Exit code 0 when every case is clean, 1 otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import re
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent / "elastimap"
MEM_LIMIT = 8 << 30  # address-space cap per case: a 10^10-pixel image must not take the machine


# ----------------------------------------------------------------------------- running a case


@dataclass
class Result:
    rc: int
    out: str
    err: str
    seconds: float
    work: Path


@dataclass
class Case:
    cid: str
    group: str
    args: list[str]
    expect: str = "refuse"  # refuse | ok | either
    names: tuple[str, ...] = ()  # the error line must contain one of these
    setup: Callable[[Path], None] | None = None
    check: Callable[[Result], str | None] | None = None
    timeout: float = 180.0
    rcs: tuple[int, ...] = (2,)


def _env(home: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        HOME=str(home),
        OMP_NUM_THREADS="1",
        MPLBACKEND="Agg",
        TMPDIR=str(home / "tmp"),
        ELASTIMAP_GAP_CACHE=str(home / "gapcache"),
        PYTHONWARNINGS="ignore",
    )
    env.pop("ELASTIMAP_DEBUG", None)
    return env


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEM_LIMIT, MEM_LIMIT))


def run_cli(args: list[str], work: Path, timeout: float = 180.0) -> Result:
    home = work.parent / ".home"
    (home / "tmp").mkdir(parents=True, exist_ok=True)
    t = time.monotonic()
    try:
        p = subprocess.run(
            [str(BIN), *args],
            cwd=work,
            env=_env(home),
            capture_output=True,
            text=True,
            errors="replace",
            timeout=timeout,
            preexec_fn=_limit_memory,
            stdin=subprocess.DEVNULL,
        )
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as e:
        rc, out, err = -999, _text(e.stdout), _text(e.stderr) + f"\n[timeout after {timeout} s]"
    return Result(rc, out, err, time.monotonic() - t, work)


def _text(b) -> str:
    if b is None:
        return ""
    return b.decode(errors="replace") if isinstance(b, bytes) else b


def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root`` but the case's ``.home``: kind, size, content hash, link target."""
    snap: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = os.path.relpath(dirpath, root)
        if rel_dir.split(os.sep)[0] == ".home":
            dirnames[:] = []
            continue
        for name in dirnames + filenames:
            p = Path(dirpath, name)
            rel = os.path.normpath(os.path.join(rel_dir, name))
            if rel.split(os.sep)[0] == ".home":
                continue
            if p.is_symlink():
                snap[rel] = ("link", os.readlink(p))
            elif p.is_dir():
                snap[rel] = ("dir",)
            else:
                try:
                    snap[rel] = ("file", p.stat().st_size, hashlib.sha256(p.read_bytes()).hexdigest())
                except OSError as e:
                    snap[rel] = ("unreadable", str(e))
    return snap


def diff(a: dict, b: dict) -> str:
    changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    return ", ".join(changed[:4]) + (f" (+{len(changed) - 4})" if len(changed) > 4 else "")


def judge(case: Case, r: Result, changed: str) -> tuple[bool, str]:
    text = r.out + r.err
    if "Traceback" in text:
        return False, "TRACEBACK " + _last(r.err)
    if r.rc == -999:
        return False, "timeout"
    lines = [ln for ln in r.err.splitlines() if ln.strip()]
    refuse_ok = r.rc in case.rcs and len(lines) == 1 and not changed
    if refuse_ok and case.names and not any(n in lines[0] for n in case.names):
        refuse_ok = False
    ok_ok = False
    why_ok = ""
    if r.rc == 0:
        why_ok = case.check(r) if case.check else None
        ok_ok = why_ok is None
    if case.expect == "refuse":
        if refuse_ok:
            return True, ""
        why = []
        if r.rc not in case.rcs:
            why.append(f"exit {r.rc}")
        if len(lines) != 1:
            why.append(f"{len(lines)} stderr lines")
        elif case.names and not any(n in lines[0] for n in case.names):
            why.append(f"line does not name {'/'.join(case.names)}")
        if changed:
            why.append(f"wrote {changed}")
        return False, "; ".join(why) + " | " + _last(r.err or r.out)
    if case.expect == "ok":
        if ok_ok:
            return True, ""
        return False, (f"exit {r.rc}" if r.rc else f"bad output: {why_ok}") + " | " + _last(r.err or r.out)
    if refuse_ok or ok_ok:
        return True, ""
    return False, f"neither clean refusal nor clean success (exit {r.rc}) | " + _last(r.err or r.out)


def _last(s: str) -> str:
    lines = [ln.strip() for ln in s.splitlines() if ln.strip()]
    return (lines[-1] if lines else "")[:200]


# ----------------------------------------------------------------------------- fixtures


def _cli(args: list[str], cwd: Path, timeout: float = 600.0) -> None:
    r = run_cli(args, cwd, timeout)
    if r.rc != 0:
        raise SystemExit(f"fixture failed: elastimap {' '.join(args)}\n{r.err[-2000:]}")


def build_fixtures(fx: Path) -> None:
    """The small valid inputs every case starts from (about a minute on the tiny mesh)."""
    if (fx / ".complete").exists():
        return
    fx.mkdir(parents=True, exist_ok=True)
    _cli(
        ["sweep", "run", "--mesh", "tiny", "--n", "16", "--phantoms", "--jobs", "1", "--out", "sw", "--no-progress"], fx
    )
    _cli(
        [
            "train",
            "--synthetic",
            "40",
            "--repeats",
            "1",
            "--epochs",
            "5",
            "--hidden",
            "4",
            "--out",
            "model",
            "--no-progress",
        ],
        fx,
    )
    _cli(["study", "image_model", "--data", "sw", "--validate", "none", "--save-model", "imodel", "--repeats", "1",
          "--k", "3", "--hidden", "4", "--epochs", "5", "--out", "imrun", "--no-progress"], fx)  # fmt: skip
    shutil.rmtree(fx / "imrun", ignore_errors=True)
    _cli(["camera", "calibrate", "--mesh", "tiny", "--frames", "2", "--out", "cal.json"], fx)
    _cli(
        ["camera", "synth", "--d", "8", "--h", "7", "--E", "50", "--mesh", "tiny", "--frames", "2", "--out", "frames"],
        fx,
    )
    _cli(["camera", "synth", "--d", "8", "--h", "7", "--E", "50", "--mesh", "tiny", "--frames", "2", "--out", "framest",
          "--format", "tiff"], fx)  # fmt: skip
    _cli(["gap", "synth", "--backend", "toy", "--n", "4", "--frames", "2", "--out", "meas", "--cache", "none"], fx)
    _cli(["solve", "--mesh", "tiny", "--image-npy", "img.npy"], fx)
    (fx / "sensor.toml").write_text(
        'name = "lab-A"\n[probe]\nfootprint = 20.0\nnu = 0.49\nlayers = [\n  { thickness = 2.0, E = 200.0 },\n'
        "  { thickness = 3.0, E = 150.0 },\n  { thickness = 5.0, E = 50.0 },\n]\n[camera]\nbits = 16\n"
    )
    (fx / "samples.csv").write_text("d,h,E\n6,8,40\n9,9,120\n")
    (fx / "feats.csv").write_text("id,O1,O2,O3\na,0.02,1.2,230\nb,0.03,1.5,260\n")
    shutil.copy(ROOT / "dataset" / "phantoms.csv", fx / "phantoms.csv")
    (fx / ".complete").write_text("ok\n")


def prepare(fx: Path, base: Path, cid: str) -> Path:
    case_root = base / re.sub(r"[^A-Za-z0-9_.-]", "_", cid)
    if case_root.exists():
        shutil.rmtree(case_root)
    work = case_root / "work"
    shutil.copytree(fx, work, symlinks=True, ignore=shutil.ignore_patterns(".complete"))
    (case_root / ".home" / "tmp").mkdir(parents=True)
    return work


# ----------------------------------------------------------------------------- file makers


def w(rel: str, content: str | bytes) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        p = work / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(content if isinstance(content, bytes) else content.encode())

    return setup


def seq(*fns: Callable[[Path], None]) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        for f in fns:
            f(work)

    return setup


def symlink(rel: str, target: str) -> Callable[[Path], None]:
    return lambda work: os.symlink(target, work / rel)


def mkdir(rel: str) -> Callable[[Path], None]:
    return lambda work: (work / rel).mkdir(parents=True, exist_ok=True)


def png_bytes(width: int, height: int, data: bytes | None = None, bit_depth: int = 16, colour: int = 0) -> bytes:
    """A PNG whose header claims ``width`` x ``height``; ``data`` = raw scanlines (None: a tiny bogus stream)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour, 0, 0, 0)
    idat = zlib.compress(data if data is not None else b"\x00" * 64)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def npy(rel: str, make: Callable[[], object], allow_pickle: bool = False) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        import numpy as np

        np.save(work / rel, make(), allow_pickle=allow_pickle)

    return setup


def edit_json(rel: str, fn: Callable[[dict], object]) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        p = work / rel
        d = json.loads(p.read_text())
        fn(d)
        p.write_text(json.dumps(d, allow_nan=True))

    return setup


def edit_text(rel: str, fn: Callable[[str], str]) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        p = work / rel
        p.write_text(fn(p.read_text()))

    return setup


def truncate(rel: str, src: str, keep: float) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        b = (work / src).read_bytes()
        (work / rel).write_bytes(b[: int(len(b) * keep)])

    return setup


def first_glob(work: Path, pattern: str) -> Path:
    return sorted(work.glob(pattern))[0]


def copy_parquet_part(rel: str, keep: float) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        b = first_glob(work, "sw/*.parquet").read_bytes()
        (work / rel).parent.mkdir(parents=True, exist_ok=True)
        (work / rel).write_bytes(b[: int(len(b) * keep)])

    return setup


def other_parquet(rel: str) -> Callable[[Path], None]:
    def setup(work: Path) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        (work / rel).parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table({"a": [1, 2], "b": ["x", "y"]}), work / rel)

    return setup


def meas_csv(fn: Callable[[list[list[str]]], None]) -> Callable[[Path], None]:
    """Edit meas/measured.csv as rows of strings (row 0 = header)."""

    def setup(work: Path) -> None:
        p = work / "meas" / "measured.csv"
        rows = [ln.split(",") for ln in p.read_text().splitlines()]
        fn(rows)
        p.write_text("\n".join(",".join(r) for r in rows) + "\n")

    return setup


def _set_col(name: str, row: int, value: str) -> Callable[[list[list[str]]], None]:
    def fn(rows: list[list[str]]) -> None:
        rows[row][rows[0].index(name)] = value

    return fn


def ccsv(rows: list[str]) -> str:
    return "\n".join(rows) + "\n"


# ----------------------------------------------------------------------------- checks


def has(*rels: str) -> Callable[[Result], str | None]:
    def check(r: Result) -> str | None:
        missing = [x for x in rels if not (r.work / x).exists()]
        return f"missing {missing}" if missing else None

    return check


def json_stdout(r: Result) -> str | None:
    try:
        json.loads(r.out)
    except ValueError as e:
        return f"stdout is not JSON ({e})"
    return None


def rows_of(sweep: str, n: int) -> Callable[[Result], str | None]:
    def check(r: Result) -> str | None:
        import pyarrow.parquet as pq

        t = pq.read_table([str(p) for p in sorted((r.work / sweep).glob("*.parquet"))])
        ids = t.column("sample_id").to_pylist()
        if len(ids) != len(set(ids)):
            return f"duplicate sample ids in {sweep}"
        return None if len(ids) == n else f"{len(ids)} rows in {sweep}, expected {n}"

    return check


def no_nan_in_stdout(r: Result) -> str | None:
    return "NaN in the answer" if re.search(r"\bnan\b", r.out, re.I) else None


# ----------------------------------------------------------------------------- the cases

T = ["--mesh", "tiny"]
BAD_TOMLS = {
    "syntax": "name = \n[probe\n",
    "layers-str": '[probe]\nlayers = "2:300"\n',
    "layer-negE": "[probe]\nlayers = [ { thickness = 2.0, E = -5.0 } ]\n",
    "layer-zero-t": "[probe]\nlayers = [ { thickness = 0.0, E = 300.0 } ]\n",
    "layers-empty": "[probe]\nlayers = []\n",
    "layer-missing-E": "[probe]\nlayers = [ { thickness = 2.0 } ]\n",
    "unknown-field": "[probe]\nfootprnt = 20.0\n",
    "unknown-section": "[lens]\nfocal = 3\n",
    "nu-half": "[tissue]\nnu = 0.5\n",
    "nu-neg": "[tissue]\nnu = -2.0\n",
    "footprint-0": "[probe]\nfootprint = 0.0\n",
    "tissue-nan": "[tissue]\nE = nan\n",
    "tissue-inf": "[tissue]\nthickness = inf\n",
    "delta-str": '[loading]\ndelta = "3"\n',
    "delta-neg": "[loading]\ndelta = -3.0\n",
    "bits-10": "[camera]\nbits = 10\n",
    "bits-huge": "[camera]\nbits = 99999999999999999999\n",
    "binning-0": "[camera]\nbinning = 0\n",
    "iface-glue": '[interface]\nmodel = "glue"\n',
    "friction-neg": "[interface]\nfriction_kt = -1.0\n",
    "name-int": "name = 5\n",
    "section-scalar": "probe = 3\n",
    "led-power-short": "[camera]\nled_power = [1.0]\n",
    "size-lt-footprint": "[tissue]\nsize = 10.0\n",
    "skin-neg": "[tissue]\nskin_thickness = -1.0\n",
    "nonlin-2": "[tissue]\nnonlinearity = 2.0\n",
    "tilt-nan": "[loading]\ntilt = nan\n",
    "force-neg": "[loading]\nforce = -10.0\n",
}


def solve_cases() -> list[Case]:
    g = "solve"
    c: list[Case] = []

    def bad(cid: str, args: list[str], *names: str, **kw) -> None:
        c.append(Case(f"solve/{cid}", g, ["solve", *T, *args], "refuse", names, **kw))

    for v in ["abc", "nan", "inf", "-inf", "-1", "0", "1e308", "1e-300", ""]:
        bad(f"d={v}", ["--d", v], "--d")
    for v in ["nan", "-5", "100", "0.5", "1e400"]:
        bad(f"h={v}", ["--h", v], "--h")
    for v in ["0", "-3", "inf", "1e308", "nan", "1e-30"]:
        bad(f"E={v}", ["--E", v], "--E")
    bad("mesh-huge", ["--mesh", "huge"], "--mesh")
    bad("mesh-empty", ["--mesh", ""], "--mesh")
    bad("interface", ["--interface", "glue"], "--interface")
    bad("geometry", ["--geometry", "warp"], "--geometry")
    bad("sizing", ["--sizing", "by_e"], "--sizing")
    for v in ["0", "-1", "25", "nan"]:
        bad(f"delta={v}", ["--delta", v], "--delta")
    for v in ["-10", "nan", "inf"]:
        bad(f"force={v}", ["--force", v], "--force")
    for v in ["0", "-1", "nan"]:
        bad(f"tissueE={v}", ["--tissue-E", v], "--tissue-E")
    for v in ["0", "-20", "1e9"]:
        bad(f"thickness={v}", ["--thickness", v], "--thickness")
    bad("thickness-vs-h", ["--thickness", "5", "--h", "7"], "--thickness", "--h", "--d")
    for v in ["0.5", "0.6", "-1.5", "nan"]:
        bad(f"nu={v}", ["--nu", v], "--nu")
    for v in ["", "2:300,3", "a:b", "2:-300", "0:300", "2:300,,3:150", "2:300:1", "2:nan", "2:inf"]:
        bad(f"layers={v!r}", ["--layers", v], "--layers")
    for v in ["0", "-0.5", "1e-9", "nan", "100"]:
        bad(f"pixel={v}", ["--pixel", v], "--pixel")
    for v in ["-1", "nan", "inf"]:
        bad(f"threshold={v}", ["--threshold", v], "--threshold")
    for v in ["3", "0", "x"]:
        bad(f"degree={v}", ["--degree", v], "--degree")
    bad("image-nodir", ["--image", "nodir/x.png"], "--image")
    bad("image-isdir", ["--image", "sw"], "--image")
    bad("image-loop", ["--image", "loop.png"], "--image", "loop.png", setup=seq(symlink("loop.png", "loop2.png"), symlink("loop2.png", "loop.png")))  # fmt: skip
    bad("image-onto-sensor", ["--sensor", "sensor.toml", "--image", "sensor.toml"], "--image", "sensor.toml")
    bad("image-npy-isdir", ["--image-npy", "frames"], "--image-npy")
    bad("image-npy-nodir", ["--image-npy", "no/such/dir/x.npy"], "--image-npy")
    bad("vtx-onto-file", ["--vtx", "cal.json"], "--vtx")
    bad("image-same-as-npy", ["--image", "same.out", "--image-npy", "same.out"], "--image", "--image-npy")
    bad("sensor-missing", ["--sensor", "nosuch.toml"], "--sensor")
    bad("sensor-dir", ["--sensor", "sw"], "--sensor")
    bad("sensor-binary", ["--sensor", "bin.toml"], "--sensor", "bin.toml", setup=w("bin.toml", os.urandom(300)))
    bad("sensor-utf16", ["--sensor", "u16.toml"], "--sensor", "u16.toml", setup=w("u16.toml", "name = 'x'\n".encode("utf-16")))  # fmt: skip
    bad("sensor-json", ["--sensor", "cal.json"], "--sensor", "cal.json")
    for k, v in BAD_TOMLS.items():
        bad(f"sensor-{k}", ["--sensor", f"{k}.toml"], "--sensor", f"{k}.toml", setup=w(f"{k}.toml", v))
    bad("unknown-flag", ["--dd", "3"], "--dd")
    bad("extra-arg", ["stray"], "stray")
    ok = "ok"
    c.append(Case("solve/ok-json", g, ["solve", *T, "--json"], ok, check=json_stdout))
    c.append(Case("solve/ok-empty-sensor", g, ["solve", *T, "--sensor", "e.toml", "--json"], ok, setup=w("e.toml", ""), check=json_stdout))  # fmt: skip
    c.append(Case("solve/ok-lab-sensor", g, ["solve", *T, "--sensor", "sensor.toml", "--json"], ok, check=json_stdout))
    c.append(Case("solve/ok-unicode-image", g, ["solve", *T, "--image", "ünï cødé ø.png"], ok, check=has("ünï cødé ø.png")))  # fmt: skip
    c.append(Case("solve/ok-force", g, ["solve", *T, "--force", "50", "--json"], ok, check=json_stdout))
    c.append(Case("solve/ok-npy", g, ["solve", *T, "--image-npy", "x.npy"], ok, check=has("x.npy")))
    return c


def sweep_cases() -> list[Case]:
    g = "sweep run"
    c: list[Case] = []
    base = ["sweep", "run", *T, "--jobs", "1", "--no-progress"]

    def bad(cid: str, args: list[str], *names: str, out: str | None = "new", **kw) -> None:
        extra = ["--out", out] if out is not None else []
        c.append(Case(f"sweep/{cid}", g, [*base, "--n", "1", *extra, *args] if "--n" not in args else [*base, *extra, *args], "refuse", names, **kw))  # fmt: skip

    for v in ["-1", "abc", "99999999999999999999", "1e3", ""]:
        bad(f"n={v!r}", ["--n", v], "--n")
    bad("seed-huge", ["--seed", "99999999999999999999999"], "--seed")
    for v in ["0", "-2", "99999", "abc"]:
        bad(f"jobs={v}", ["--jobs", v], "--jobs")
    bad("mesh", ["--mesh", "xx"], "--mesh")
    bad("design", ["--design", "grid"], "--design")
    bad("interface", ["--interface", "x"], "--interface")
    bad("geometry", ["--geometry", "x"], "--geometry")
    bad("sizing", ["--sizing", "x"], "--sizing")
    for v in ["d=5:2", "d=a:b", "q=1:2", "d=0:5", "E=-1:5", "E=0:100:log", "d=2:15:cubic", "d=2", "",
              "d=nan:5", "d=2:inf", "h=auto:5", "d=2:15,d=3:4", "d=2:15,,E=1:2", "E=1:1e308"]:  # fmt: skip
        bad(f"ranges={v!r}", ["--ranges", v], "--ranges")
    bad("samples-missing", ["--samples", "nosuch.csv"], "--samples", "nosuch.csv")
    bad("samples-dir", ["--samples", "sw"], "--samples")
    bad("samples-empty", ["--samples", "e.csv"], "--samples", "e.csv", setup=w("e.csv", ""))
    bad("samples-noE", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h\n5,8\n"))
    bad("samples-text", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h,E\nbig,8,40\n"))
    bad("samples-nan", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h,E\nnan,8,40\n"))
    bad("samples-negE", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h,E\n5,8,-40\n"))
    bad("samples-dupid", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "sample_id,d,h,E\na,5,8,40\na,6,8,40\n"))  # fmt: skip
    bad("samples-dupcol", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h,E,E\n5,8,40,80\n"))
    bad("samples-deep", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h,E\n8,19,40\n"))
    bad("samples-tissueE0", ["--samples", "s.csv"], "--samples", "s.csv", setup=w("s.csv", "d,h,E,tissue_E\n5,8,40,0\n"))  # fmt: skip
    bad("samples-garbage-parquet", ["--samples", "g.parquet"], "--samples", "g.parquet", setup=w("g.parquet", os.urandom(500)))  # fmt: skip
    bad("samples-binary-csv", ["--samples", "g.csv"], "--samples", "g.csv", setup=w("g.csv", os.urandom(500)))
    # sample ids never become file names (the sweep's markers hash them): either answer is clean
    c.append(Case("sweep/samples-id-slash", g, [*base, "--n", "1", "--out", "new", "--samples", "s.csv"], "either", ("--samples", "s.csv"), setup=w("s.csv", "sample_id,d,h,E\n../a,5,8,40\n")))  # fmt: skip
    bad("out-is-file", [], "--out", out="cal.json")
    bad("out-foreign-folder", [], "--out", out="model")
    bad("out-other-design", ["--n", "3", "--seed", "5"], "--out", "--append", out="sw")
    bad("out-empty", [], "--out", out="")
    bad("out-other-sensor", ["--sensor", "sensor.toml"], "--sensor", "--out", out="sw")
    bad("sensor-bad", ["--sensor", "b.toml"], "--sensor", setup=w("b.toml", BAD_TOMLS["layer-negE"]))
    for v in ["-1", "nan"]:
        bad(f"timeout={v}", ["--timeout", v], "--timeout")
    for v in ["0", "-1", "99999999999999999999", "x"]:
        bad(f"batch-rows={v}", ["--batch-rows", v], "--batch-rows")
    for v in ["-1", "nan"]:
        bad(f"connect-timeout={v}", ["--connect-timeout", v], "--connect-timeout")
    bad("worker-wait", ["--worker-wait", "-1"], "--worker-wait")
    for v in ["notaport", "127.0.0.1:99999", "::::", ""]:
        bad(f"dashboard={v!r}", ["--dashboard", v], "--dashboard")
    bad("scheduler-dead", ["--scheduler", "tcp://127.0.0.1:1", "--connect-timeout", "2"], "--scheduler", rcs=(2, 3))
    bad("scheduler-garbage", ["--scheduler", "not a url", "--connect-timeout", "2"], "--scheduler", rcs=(2, 3))
    c.append(Case("sweep/ok-unicode-out", g, [*base, "--n", "2", "--out", "swé ü"], "ok", check=rows_of("swé ü", 2)))
    c.append(Case("sweep/ok-resume-same", g, [*base, "--n", "16", "--phantoms", "--out", "sw"], "ok", check=rows_of("sw", 25)))  # fmt: skip
    c.append(Case("sweep/ok-samples", g, [*base, "--samples", "samples.csv", "--out", "ss"], "ok", check=rows_of("ss", 2)))  # fmt: skip
    c.append(Case("sweep/edge-seed-neg", g, [*base, "--n", "1", "--seed", "-1", "--out", "sn"], "either", ("--seed",)))
    c.append(Case("sweep/edge-samples-header-only", g, [*base, "--samples", "h.csv", "--out", "sh"], "either", ("--samples", "h.csv"), setup=w("h.csv", "d,h,E\n")))  # fmt: skip
    c.append(Case("sweep/edge-bom", g, [*base, "--samples", "b.csv", "--out", "sb"], "either", ("--samples", "b.csv"), setup=w("b.csv", "\ufeffd,h,E\n6,8,40\n".encode("utf-8"))))  # fmt: skip

    gb = "sweep bench"
    bench = ["sweep", "bench", *T, "--n", "1"]
    for v in ["0", "a,b", "", "1,,2", "-1", "99999"]:
        c.append(Case(f"bench/jobs-list={v!r}", gb, [*bench, "--jobs-list", v], "refuse", ("--jobs-list",)))
    c.append(Case("bench/paths", gb, [*bench, "--compare", "--paths", "bogus"], "refuse", ("--paths",)))
    c.append(Case("bench/out-file", gb, [*bench, "--out", "cal.json"], "refuse", ("--out",)))
    c.append(Case("bench/n-neg", gb, ["sweep", "bench", *T, "--n", "-1"], "refuse", ("--n",)))
    c.append(Case("bench/out-foreign", gb, [*bench, "--jobs-list", "1", "--out", "model"], "refuse", ("--out",)))
    c.append(Case("bench/ok", gb, [*bench, "--jobs-list", "1", "--out", "bo"], "ok"))
    return c


def dataset_cases() -> list[Case]:
    c: list[Case] = []
    trunc = copy_parquet_part("tr/b-1.parquet", 0.5)

    def add(sub: str, cid: str, args: list[str], *names: str, expect: str = "refuse", **kw) -> None:
        c.append(Case(f"dataset-{sub}/{cid}", f"dataset {sub}", ["dataset", sub, *args], expect, names, **kw))

    for sub in ["inspect", "export", "compact", "plot"]:
        extra = ["--out", "figs"] if sub == "plot" else []
        add(sub, "missing", ["nosuch", *extra], "nosuch")
        add(sub, "empty-dir", ["ed", *extra], "ed", setup=mkdir("ed"))
        add(sub, "garbage-parquet", ["g.parquet", *extra], "g.parquet", setup=w("g.parquet", os.urandom(700)))
        add(sub, "garbage-in-dir", ["gd", *extra], "gd", "b-1.parquet", setup=w("gd/b-1.parquet", os.urandom(700)))
        add(sub, "truncated", ["tr", *extra], "tr", "b-1.parquet", setup=trunc)
        add(sub, "other-schema", ["os.parquet", *extra], "os.parquet", setup=other_parquet("os.parquet"))
        add(sub, "csv-file", ["samples.csv", *extra], "samples.csv")
        add(sub, "empty-string", ["", *extra], "PATH", "''")
    add("inspect", "top=-1", ["sw", "--top", "-1"], "--top")
    add("inspect", "top=abc", ["sw", "--top", "abc"], "--top")
    add("inspect", "top=huge", ["sw", "--top", "99999999999999999999"], "--top")
    add("inspect", "ok", ["sw"], expect="ok")
    add("inspect", "ok-json", ["sw", "--json"], expect="ok", check=json_stdout)
    add("inspect", "ok-file", ["one.parquet"], expect="ok", setup=lambda wk: shutil.copy(first_glob(wk, "sw/*.parquet"), wk / "one.parquet"))  # fmt: skip
    add("export", "out-onto-manifest", ["sw", "--out", "sw/_sweep.json"], "--out")
    add("export", "out-dir", ["sw", "--out", "sw"], "--out")
    add("export", "out-nodir", ["sw", "--out", "nodir/x.csv"], "--out")
    add("export", "out-onto-input", ["samples.csv", "--out", "samples.csv"], "--out", "samples.csv")
    add("export", "status", ["sw", "--status", "bogus"], "--status")
    add("export", "out-loop", ["sw", "--out", "l.csv"], "--out", "l.csv", setup=seq(symlink("l.csv", "l2.csv"), symlink("l2.csv", "l.csv")))  # fmt: skip
    add("export", "ok", ["sw", "--out", "x.csv"], expect="ok", check=has("x.csv"))
    add("export", "ok-stdout", ["sw", "--out", "-"], expect="ok", check=lambda r: None if r.out.count("\n") >= 26 else "short CSV")  # fmt: skip
    add("export", "ok-image", ["sw", "--out", "x.csv", "--image-column"], expect="ok", check=has("x.csv"))
    add(
        "export",
        "edge-existing-default",
        ["sw"],
        "sw.csv",
        "--out",
        expect="either",
        setup=w("sw.csv", "my,own\n1,2\n"),
    )
    for v in ["0", "-1", "99999999999999999999", "x"]:
        add("compact", f"batch-rows={v}", ["sw", "--batch-rows", v], "--batch-rows")
    add("compact", "json-file", ["cal.json"], "cal.json")
    add("compact", "ok", ["sw"], expect="ok", check=rows_of("sw", 25))
    add("plot", "out-missing", ["sw"], "--out")
    add("plot", "out-file", ["sw", "--out", "cal.json"], "--out")
    add("plot", "out-onto-data", ["sw", "--out", "sw"], "--out")
    for v in ["-1", "99999999999999999999", "x"]:
        add("plot", f"n-images={v}", ["sw", "--out", "figs", "--n-images", v], "--n-images")
    add("plot", "ok", ["sw", "--out", "figs"], expect="ok", check=has("figs"))
    add("plot", "edge-n-images-0", ["sw", "--out", "figs", "--n-images", "0"], "--n-images", expect="either")
    return c


def train_cases() -> list[Case]:
    g = "train"
    c: list[Case] = []
    quick = ["--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress", "--workers", "1"]

    def bad(cid: str, args: list[str], *names: str, data: list[str] | None = None, **kw) -> None:
        d = ["--synthetic", "30"] if data is None else data
        c.append(Case(f"train/{cid}", g, ["train", *d, *quick, "--out", "run", *args], "refuse", names, **kw))

    bad("data-missing", [], "--data", data=["--data", "nosuch"])
    bad("data-garbage", [], "--data", "g.parquet", data=["--data", "g.parquet"], setup=w("g.parquet", os.urandom(600)))
    bad("data-empty-dir", [], "--data", "ed", data=["--data", "ed"], setup=mkdir("ed"))
    bad("data-other-schema", [], "--data", "os.parquet", data=["--data", "os.parquet"], setup=other_parquet("os.parquet"))  # fmt: skip
    bad("data-truncated", [], "--data", "tr", data=["--data", "tr"], setup=copy_parquet_part("tr/b-1.parquet", 0.4))
    bad("data-csv", [], "--data", data=["--data", "samples.csv"])
    for v in ["0", "-5", "abc", "99999999999999999999", "1"]:
        bad(f"synthetic={v}", [], "--synthetic", data=["--synthetic", v])
    bad("both-data", [], "--synthetic", "--data", data=["--synthetic", "30", "--data", "sw"])
    bad("neither", [], "--data", "--synthetic", data=[])
    bad("algo", ["--algo", "adam"], "--algo")
    bad("validate", ["--validate", "kfold"], "--validate")
    for flag in ["--repeats", "--epochs"]:
        for v in ["0", "-1", "99999999999999999999"]:
            bad(f"{flag}={v}", [flag, v], flag)
    for v in ["", "0", "-3", "a,b", "25,10:bogus", "25,,10", "3:purelin:x", "100000000000"]:
        bad(f"hidden={v!r}", ["--hidden", v], "--hidden")
    bad("activation", ["--activation", "relu"], "--activation")
    bad("activation-empty", ["--activation", ""], "--activation")
    for v in ["-0.1", "nan", "inf"]:
        bad(f"feature-noise={v}", ["--feature-noise", v], "--feature-noise")
    for v in ["0", "1", "1.5", "-0.2", "nan"]:
        bad(f"test-split={v}", ["--test-split", v], "--test-split")
    for v in ["1", "-0.1", "nan"]:
        bad(f"val-fraction={v}", ["--val-fraction", v], "--val-fraction")
    bad("seed-huge", ["--seed", "99999999999999999999999"], "--seed")
    c.append(Case("train/out-existing", g, ["train", "--synthetic", "30", *quick, "--out", "model"], "refuse", ("--out", "--overwrite")))  # fmt: skip
    c.append(Case("train/out-is-data", g, ["train", "--data", "sw", *quick, "--out", "sw", "--overwrite"], "refuse", ("--out",)))  # fmt: skip
    c.append(Case("train/out-inside-data", g, ["train", "--data", "sw", *quick, "--out", "sw/run"], "refuse", ("--out",)))  # fmt: skip
    c.append(Case("train/out-holds-data", g, ["train", "--data", "w/sw", *quick, "--out", "w", "--overwrite"], "refuse", ("--out",), setup=lambda wk: shutil.copytree(wk / "sw", wk / "w" / "sw")))  # fmt: skip
    c.append(Case("train/out-file", g, ["train", "--synthetic", "30", *quick, "--out", "cal.json"], "refuse", ("--out",)))  # fmt: skip
    c.append(Case("train/out-file-overwrite", g, ["train", "--synthetic", "30", *quick, "--out", "cal.json", "--overwrite"], "refuse", ("--out",)))  # fmt: skip
    c.append(Case("train/overwrite-foreign", g, ["train", "--synthetic", "30", *quick, "--out", "frames", "--overwrite"], "refuse", ("--out",)))  # fmt: skip
    bad("device", ["--device", "tpu"], "--device")
    for v in ["-1", "99999999999999999999"]:
        bad(f"threads={v}", ["--threads", v], "--threads")
    for v in ["-1", "99999"]:
        bad(f"workers={v}", ["--workers", v], "--workers")
    ok = [*quick]
    c.append(Case("train/ok-unicode", g, ["train", "--synthetic", "30", *ok, "--out", "rün ø"], "ok", check=has("rün ø/run.json")))  # fmt: skip
    c.append(Case("train/ok-loocv-lm", g, ["train", "--synthetic", "12", "--algo", "lm", "--validate", "loocv", *ok, "--out", "lo", "--no-model"], "ok", check=has("lo/results.csv")))  # fmt: skip
    c.append(Case("train/ok-data", g, ["train", "--data", "sw", *ok, "--out", "rd"], "ok", check=has("rd/run.json")))
    c.append(Case("train/ok-overwrite", g, ["train", "--synthetic", "30", *ok, "--out", "model", "--overwrite"], "ok", check=has("model/run.json")))  # fmt: skip
    c.append(Case("train/edge-seed-neg", g, ["train", "--synthetic", "30", *ok, "--seed", "-1", "--out", "sn"], "either", ("--seed",)))  # fmt: skip
    c.append(Case("train/edge-device-cuda", g, ["train", "--synthetic", "30", *ok, "--device", "cuda", "--out", "cu"], "either", ("--device",)))  # fmt: skip
    return c


def camera_cases() -> list[Case]:
    c: list[Case] = []
    syn = ["camera", "synth", *T, "--d", "8", "--h", "7", "--E", "50", "--frames", "1"]

    def synth(cid: str, args: list[str], *names: str, out: str = "cs", expect: str = "refuse", **kw) -> None:
        c.append(Case(f"camera-synth/{cid}", "camera synth", [*syn, "--out", out, *args], expect, names, **kw))

    c.append(Case("camera-synth/no-E", "camera synth", ["camera", "synth", *T, "--d", "8", "--h", "7", "--out", "cs"], "refuse", ("--E",)))  # fmt: skip
    for flag in ["--d", "--h", "--E"]:
        for v in ["nan", "-1", "inf", "0"]:
            synth(f"{flag}={v}", [flag, v], flag)
    for v in ["0", "-1", "99999999999999999999", "abc", "100000"]:
        synth(f"frames={v}", ["--frames", v], "--frames")
    synth("out-file", [], "--out", out="cal.json")
    for v in ["a/b", "../x", "", "/abs"]:
        synth(f"name={v!r}", ["--name", v], "--name")
    synth("format", ["--format", "bmp"], "--format")
    synth("bits", ["--bits", "12"], "--bits")
    for v in ["0", "-1", "100000", "99999999999999999999"]:
        synth(f"binning={v}", ["--binning", v], "--binning")
    for v in ["-1", "99999999999999999999999"]:
        synth(f"seed={v}", ["--seed", v], "--seed", expect="either" if v == "-1" else "refuse")
    for v in ["-1", "nan", "inf", "1e308"]:
        synth(f"noise-scale={v}", ["--noise-scale", v], "--noise-scale")
    synth("tissue-E=0", ["--tissue-E", "0"], "--tissue-E")
    synth("delta=-1", ["--delta", "-1"], "--delta")
    synth("delta=nan", ["--delta", "nan"], "--delta")
    synth("sensor-json-bad", ["--sensor", "s.json"], "--sensor", "s.json", setup=w("s.json", "{bits: 16"))
    synth("sensor-json-unknown", ["--sensor", "s.json"], "--sensor", "s.json", setup=w("s.json", '{"lens": 3}'))
    synth("sensor-json-bits", ["--sensor", "s.json"], "--sensor", "s.json", setup=w("s.json", '{"bits": 7}'))
    synth("sensor-json-list", ["--sensor", "s.json"], "--sensor", "s.json", setup=w("s.json", "[1, 2]"))
    synth("sensor-json-nan", ["--sensor", "s.json"], "--sensor", "s.json", setup=w("s.json", '{"vignetting": NaN}'))
    synth("sensor-toml-bad", ["--sensor", "s.toml"], "--sensor", "s.toml", setup=w("s.toml", BAD_TOMLS["bits-10"]))
    synth("ok-tiff", ["--format", "tiff"], expect="ok", check=has("cs"))
    synth("ok-noise-free", ["--noise-scale", "0", "--name", "ünï"], expect="ok", check=has("cs"))
    synth("edge-existing-frames", ["--frames", "2"], "--out", "--name", out="frames", expect="either")

    # features
    fe = ["camera", "features"]
    L, B = "frames/synthetic_d8_h7_E50_f00*.png", "frames/*background*.png"
    LT, BT = "framest/synthetic_d8_h7_E50_f00*.tif*", "framest/*background*.tif*"

    def feat(cid: str, args: list[str], *names: str, expect: str = "refuse", **kw) -> None:
        c.append(Case(f"camera-features/{cid}", "camera features", [*fe, *args], expect, names, **kw))

    feat("images-nomatch", ["--images", "nomatch*.png", "--background", B], "--images")
    feat("background-nomatch", ["--images", L, "--background", "nomatch*.png"], "--background")
    feat("corrupt-png", ["--images", "c.png", "--background", B], "c.png", setup=w("c.png", os.urandom(800)))
    feat("empty-png", ["--images", "z.png", "--background", B], "z.png", setup=w("z.png", b""))
    feat("text-png", ["--images", "t.png", "--background", B], "t.png", setup=w("t.png", "hello\n"))
    feat("truncated-png", ["--images", "tr.png", "--background", B], "tr.png", setup=lambda wk: (wk / "tr.png").write_bytes(first_glob(wk, L).read_bytes()[:150]))  # fmt: skip
    feat("png-bomb-header", ["--images", "bomb.png", "--background", B], "bomb.png", setup=w("bomb.png", png_bytes(100000, 100000)))  # fmt: skip
    feat("png-zero-size", ["--images", "zs.png", "--background", B], "zs.png", setup=w("zs.png", png_bytes(0, 0)))
    feat("corrupt-tiff", ["--images", "c.tif", "--background", BT], "c.tif", setup=w("c.tif", b"II*\x00" + os.urandom(400)))  # fmt: skip
    feat("mixed-size", ["--images", L, "--background", "small.png"], "small.png", "--background", setup=w("small.png", png_bytes(8, 8, b"".join(b"\x00" + b"\x00\x10" * 8 for _ in range(8)))))  # fmt: skip
    feat("dir-as-images", ["--images", "frames", "--background", B], "--images", "frames")
    feat("etc-passwd", ["--images", "/etc/passwd", "--background", B], "/etc/passwd", "--images")
    feat("etc-glob", ["--images", "/etc/*", "--background", B], "--images", "/etc")
    for v in ["-1", "nan", "2"]:
        feat(f"o3-threshold={v}", ["--images", L, "--background", B, "--o3-threshold", v], "--o3-threshold")
    for v in ["-1", "nan", "1e308"]:
        feat(f"smooth-px={v}", ["--images", L, "--background", B, "--smooth-px", v], "--smooth-px")
    feat("combine", ["--images", L, "--background", B, "--combine", "median"], "--combine")
    feat("sensor-bad", ["--images", L, "--background", B, "--sensor", "s.toml"], "--sensor", setup=w("s.toml", BAD_TOMLS["syntax"]))  # fmt: skip
    feat("no-background", ["--images", L], "--background")
    feat("same-files", ["--images", B, "--background", B], "--images", "--background", expect="either")
    feat("ok", ["--images", L, "--background", B, "--json"], expect="ok", check=json_stdout)
    feat("ok-tiff", ["--images", LT, "--background", BT], expect="ok")
    feat("ok-mean-features", ["--images", L, "--background", B, "--combine", "mean-features"], expect="ok")
    feat("edge-mixed-format", ["--images", L, "--background", BT], "--background", expect="either")
    feat("edge-rgb", ["--images", "rgb.png", "--background", B], "rgb.png", expect="either", setup=w("rgb.png", png_bytes(139, 104, b"".join(b"\x00" + b"\x80" * (139 * 3) for _ in range(104)), bit_depth=8, colour=2)))  # fmt: skip

    # calibrate
    cal = ["camera", "calibrate", *T, "--frames", "2"]

    def calib(cid: str, args: list[str], *names: str, out: str = "c2.json", expect: str = "refuse", **kw) -> None:
        c.append(Case(f"camera-calibrate/{cid}", "camera calibrate", [*cal, "--out", out, *args], expect, names, **kw))

    calib("out-nodir", [], "--out", out="nodir/c.json")
    calib("out-dir", [], "--out", out="sw")
    calib("out-onto-phantoms", ["--phantoms", "phantoms.csv"], "--out", out="phantoms.csv")
    calib("plot-same-as-out", ["--plot", "c2.json"], "--plot")
    calib("plot-dir", ["--plot", "sw"], "--plot")
    calib("plot-nodir", ["--plot", "nodir/p.png"], "--plot")
    for v in ["1", "0", "-1", "99999999999999999999"]:
        calib(f"frames={v}", ["--frames", v], "--frames")
    calib("phantoms-missing", ["--phantoms", "nosuch.csv"], "--phantoms")
    calib("phantoms-noE", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "name,d,h\na,5,8\nb,6,8\n"))
    calib("phantoms-nan", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "name,d,h,E\na,nan,8,40\nb,6,8,50\nc,7,9,60\n"))  # fmt: skip
    calib("phantoms-negd", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "name,d,h,E\na,-5,8,40\nb,6,8,50\nc,7,9,60\n"))  # fmt: skip
    calib("phantoms-dup", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "name,d,h,E\na,5,8,40\na,6,8,50\nc,7,9,60\n"))  # fmt: skip
    calib("phantoms-one", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "name,d,h,E\na,5,8,40\n"))
    calib("phantoms-empty", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", ""))
    calib("phantoms-slash", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "name,d,h,E\na/b,5,8,40\nb,6,8,50\nc,7,9,60\n"))  # fmt: skip
    calib("fem-missing", ["--fem-features", "nosuch.csv"], "--fem-features")
    calib("fem-nan", ["--fem-features", "f.csv"], "--fem-features", "f.csv", setup=w("f.csv", "name,O1,O2,O3\nsize-1,nan,1,2\n"))  # fmt: skip
    calib("fem-text", ["--fem-features", "f.csv"], "--fem-features", "f.csv", setup=w("f.csv", "name,O1,O2,O3\nsize-1,x,1,2\n"))  # fmt: skip
    calib("fem-empty", ["--fem-features", "f.csv"], "--fem-features", "f.csv", setup=w("f.csv", "name,O1,O2,O3\n"))
    calib("fem-wrong-names", ["--fem-features", "f.csv"], "--fem-features", "f.csv", setup=w("f.csv", "name,O1,O2,O3\nzz,0.02,1,200\n"))  # fmt: skip
    calib("fem-garbage-parquet", ["--fem-features", "g.parquet"], "--fem-features", "g.parquet", setup=w("g.parquet", os.urandom(300)))  # fmt: skip
    calib("camcsv-missing", ["--camera-csv", "nosuch.csv"], "--camera-csv")
    calib("camcsv-nomatch", ["--camera-csv", "cc.csv"], "--camera-csv", "cc.csv", "nomatch", setup=w("cc.csv", "name,images,background\nsize-1,nomatch*.png,nomatch*.png\n"))  # fmt: skip
    calib("camcsv-dotdot", ["--camera-csv", "sub/cc.csv"], "--allow-outside", setup=w("sub/cc.csv", "name,images,background\nsize-1,../frames/*_f00*.png,../frames/*background*\n"))  # fmt: skip
    calib("camcsv-abs", ["--camera-csv", "cc.csv"], "--allow-outside", setup=w("cc.csv", "name,images,background\nsize-1,/etc/passwd,/etc/passwd\n"))  # fmt: skip
    calib("camcsv-nocols", ["--camera-csv", "cc.csv"], "--camera-csv", "cc.csv", setup=w("cc.csv", "name,imgs\nsize-1,x\n"))  # fmt: skip
    calib("camcsv-unknown-name", ["--camera-csv", "cc.csv"], "--camera-csv", "cc.csv", "zz", setup=w("cc.csv", "name,images,background\nzz,frames/*_f00*.png,frames/*background*\n"))  # fmt: skip
    calib("mesh", ["--mesh", "x"], "--mesh")
    for v in ["nan", "-1"]:
        calib(f"delta={v}", ["--delta", v], "--delta")
    calib("noise-scale", ["--noise-scale", "nan"], "--noise-scale")
    calib("bits", ["--bits", "7"], "--bits")
    calib("binning", ["--binning", "0"], "--binning")
    calib("o3-threshold", ["--o3-threshold", "nan"], "--o3-threshold")
    calib("smooth-px", ["--smooth-px", "-1"], "--smooth-px")
    calib("combine", ["--combine", "x"], "--combine")
    calib("format", ["--write-frames", "wf", "--format", "gif"], "--format")
    calib("write-frames-file", ["--write-frames", "cal.json"], "--write-frames")
    calib("sensor-bad", ["--sensor", "s.toml"], "--sensor", setup=w("s.toml", BAD_TOMLS["nu-half"]))
    calib("seed-huge", ["--seed", "99999999999999999999999"], "--seed")
    calib("ok-fem-sweep", ["--fem-features", "sw"], expect="ok", check=has("c2.json"))
    calib("ok-unicode", [], out="cälib ø.json", expect="ok", check=has("cälib ø.json"))
    calib("edge-existing-out", [], "--out", out="cal.json", expect="either")
    return c


def _model_json(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    return edit_json("model/model-scg/model.json", fn)


def _cal(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    return edit_json("cal.json", fn)


def infer_cases() -> list[Case]:
    g = "camera infer"
    c: list[Case] = []
    M = ["--model", "model/model-scg"]
    C = ["--calibration", "cal.json"]
    F = ["--features", "0.02", "1.2", "230"]

    def bad(cid: str, args: list[str], *names: str, expect: str = "refuse", **kw) -> None:
        c.append(Case(f"infer/{cid}", g, ["camera", "infer", *args], expect, names, **kw))

    bad("model-missing", ["--model", "nosuch", *C, *F], "--model")
    bad("model-empty-dir", ["--model", "ed", *C, *F], "--model", setup=mkdir("ed"))
    bad("model-file", ["--model", "cal.json", *C, *F], "--model")
    bad("model-sweep", ["--model", "sw", *C, *F], "--model")
    bad("model-json-garbage", [*M, *C, *F], "--model", "model.json", setup=w("model/model-scg/model.json", "{not json"))
    bad("model-json-array", [*M, *C, *F], "--model", "model.json", setup=w("model/model-scg/model.json", "[]"))
    bad("model-nan-range", [*M, *C, *F], "--model", "model.json", setup=_model_json(lambda d: d["feature_range"][0].__setitem__(0, float("nan"))))  # fmt: skip
    bad("model-inverted-range", [*M, *C, *F], "--model", "model.json", setup=_model_json(lambda d: d.__setitem__("target_range", [d["target_range"][1], d["target_range"][0]])))  # fmt: skip
    bad("model-missing-key", [*M, *C, *F], "--model", "model.json", setup=_model_json(lambda d: d.pop("scaling")))
    bad("model-nmembers-str", [*M, *C, *F], "--model", "model.json", setup=_model_json(lambda d: d.__setitem__("n_members", "many")))  # fmt: skip
    bad("model-weights-missing", [*M, *C, *F], "--model", "ensemble", "weights", setup=lambda wk: [p.unlink() for p in (wk / "model/model-scg").glob("*.safetensors")])  # fmt: skip
    bad("model-weights-garbage", [*M, *C, *F], "--model", "ensemble", "weights", "sha", setup=lambda wk: [p.write_bytes(os.urandom(200)) for p in (wk / "model/model-scg").glob("*.safetensors")])  # fmt: skip
    bad("model-weights-escape", [*M, *C, *F], "--model", "weights_file", setup=_model_json(lambda d: d.__setitem__("weights_file", "../../cal.json")))  # fmt: skip
    bad("cal-missing", [*M, "--calibration", "nosuch.json", *F], "--calibration")
    bad("cal-garbage", [*M, "--calibration", "g.json", *F], "--calibration", "g.json", setup=w("g.json", "{"))
    bad("cal-array", [*M, "--calibration", "g.json", *F], "--calibration", "g.json", setup=w("g.json", "[1]"))
    bad("cal-nan-slope", [*M, *C, *F], "--calibration", "cal.json", setup=_cal(lambda d: d["fits"]["O1"].__setitem__("slope", float("nan"))))  # fmt: skip
    bad("cal-zero-slope", [*M, *C, *F], "--calibration", "cal.json", setup=_cal(lambda d: d["fits"]["O2"].__setitem__("slope", 0.0)))  # fmt: skip
    bad("cal-slope-str", [*M, *C, *F], "--calibration", "cal.json", setup=_cal(lambda d: d["fits"]["O2"].__setitem__("slope", "1")))  # fmt: skip
    bad("cal-no-fits", [*M, *C, *F], "--calibration", "cal.json", setup=_cal(lambda d: d.pop("fits")))
    bad("cal-is-model", [*M, "--calibration", "model/model-scg/model.json", *F], "--calibration")
    bad("cal-empty-file", [*M, "--calibration", "e.json", *F], "--calibration", "e.json", setup=w("e.json", ""))
    for vals in [["a", "b", "c"], ["nan", "1", "2"], ["inf", "1", "2"], ["-1", "1", "2"], ["0.02", "1e308", "230"]]:
        bad(f"features={'_'.join(vals)}", [*M, *C, "--features", *vals], "--features")
    bad("features-two", [*M, *C, "--features", "1", "2"], "--features")
    bad("features-no-cal", [*M, *F], "--calibration")
    bad("no-input", [*M, *C], "--features", "--images", "--csv")
    bad("features-and-csv", [*M, *C, *F, "--csv", "feats.csv"], "--features", "--csv")
    bad("csv-missing", [*M, *C, "--csv", "nosuch.csv"], "--csv")
    bad("csv-empty", [*M, *C, "--csv", "e.csv"], "--csv", "e.csv", setup=w("e.csv", ""))
    bad("csv-no-O3", [*M, *C, "--csv", "f.csv"], "--csv", "f.csv", "O3", setup=w("f.csv", "id,O1,O2\na,0.02,1.2\n"))
    bad("csv-dup-O3", [*M, *C, "--csv", "f.csv"], "--csv", "f.csv", "O3", setup=w("f.csv", "id,O1,O2,O3,O3\na,0.02,1.2,230,1\n"))  # fmt: skip
    bad("csv-nan", [*M, *C, "--csv", "f.csv"], "--csv", "f.csv", setup=w("f.csv", "id,O1,O2,O3\na,nan,1.2,230\n"))
    bad("csv-text", [*M, *C, "--csv", "f.csv"], "--csv", "f.csv", setup=w("f.csv", "id,O1,O2,O3\na,x,1.2,230\n"))
    bad("csv-dup-id", [*M, *C, "--csv", "f.csv"], "--csv", "f.csv", "a", setup=w("f.csv", "id,O1,O2,O3\na,0.02,1.2,230\na,0.03,1.5,260\n"))  # fmt: skip
    bad("csv-images-dotdot", [*M, *C, "--csv", "sub/f.csv"], "--allow-outside", setup=w("sub/f.csv", "id,images,background\na,../frames/*_f00*.png,../frames/*background*\n"))  # fmt: skip
    bad("csv-images-etc", [*M, *C, "--csv", "f.csv"], "--allow-outside", setup=w("f.csv", "id,images,background\na,/etc/*,/etc/*\n"))  # fmt: skip
    bad("csv-femimage-dotdot", ["--model", "imodel", "--csv", "sub/f.csv"], "--allow-outside", setup=w("sub/f.csv", "id,fem_image\na,../img.npy\n"))  # fmt: skip
    bad("csv-femimage-missing", ["--model", "imodel", "--csv", "f.csv"], "--csv", "nosuch.npy", setup=w("f.csv", "id,fem_image\na,nosuch.npy\n"))  # fmt: skip
    bad("csv-binary", [*M, *C, "--csv", "f.csv"], "--csv", "f.csv", setup=w("f.csv", os.urandom(400)))
    I = ["--model", "imodel"]  # noqa: E741
    bad("femimage-feature-model", [*M, "--fem-image", "img.npy"], "--fem-image", "--model")
    bad("femimage-missing", [*I, "--fem-image", "nosuch.npy"], "--fem-image")
    bad("femimage-garbage", [*I, "--fem-image", "g.npy"], "--fem-image", "g.npy", setup=w("g.npy", os.urandom(300)))
    bad("femimage-pickle", [*I, "--fem-image", "p.npy"], "--fem-image", "p.npy", setup=npy("p.npy", lambda: __import__("numpy").array([{"a": 1}], dtype=object), allow_pickle=True))  # fmt: skip
    bad("femimage-shape", [*I, "--fem-image", "s.npy"], "--fem-image", "s.npy", setup=npy("s.npy", lambda: __import__("numpy").zeros((3, 3))))  # fmt: skip
    bad("femimage-nan", [*I, "--fem-image", "n.npy"], "--fem-image", "n.npy", setup=lambda wk: __import__("numpy").save(wk / "n.npy", __import__("numpy").load(wk / "img.npy") * float("nan")))  # fmt: skip
    bad("femimage-4d", [*I, "--fem-image", "q.npy"], "--fem-image", "q.npy", setup=npy("q.npy", lambda: __import__("numpy").zeros((1, 1, 3, 3))))  # fmt: skip
    bad("femimage-empty", [*I, "--fem-image", "e.npy"], "--fem-image", "e.npy", setup=npy("e.npy", lambda: __import__("numpy").zeros((0, 5, 5))))  # fmt: skip
    bad("femimage-zero", [*I, "--fem-image", "z.npy"], "--fem-image", "z.npy", expect="either", setup=lambda wk: __import__("numpy").save(wk / "z.npy", __import__("numpy").load(wk / "img.npy") * 0))  # fmt: skip
    bad("identifiability-empty", [*M, *C, *F, "--identifiability", ""], "--identifiability")
    bad("identifiability-missing", [*M, *C, *F, "--identifiability", "nosuch.npz"], "--identifiability")
    bad("identifiability-garbage", [*M, *C, *F, "--identifiability", "g.npz"], "--identifiability", "g.npz", setup=w("g.npz", os.urandom(300)))  # fmt: skip
    for v in ["0", "-1", "nan"]:
        bad(f"crb-limit={v}", [*M, *C, *F, "--crb-limit", v], "--crb-limit")
    for v in ["0", "-1", "nan"]:
        bad(f"image-noise={v}", [*I, "--fem-image", "img.npy", "--refine", *T, "--image-noise", v], "--image-noise")
    bad("refine-feature-model", [*M, *C, *F, "--refine"], "--refine")
    bad("refine-correct-bogus", [*I, "--fem-image", "img.npy", "--refine", *T, "--refine-correct", "ultra"], "--refine-correct")  # fmt: skip
    bad("refine-correct-coarser", [*I, "--fem-image", "img.npy", "--refine", "--mesh", "coarse", "--refine-correct", "tiny"], "--refine-correct")  # fmt: skip
    bad("mesh-bogus", [*I, "--fem-image", "img.npy", "--refine", "--mesh", "x"], "--mesh")
    bad("out-txt", [*M, *C, *F, "--out", "r.txt"], "--out")
    bad("out-onto-model", [*M, *C, *F, "--out", "model/model-scg/model.json"], "--out")
    bad("out-onto-cal", [*M, *C, *F, "--out", "cal.json"], "--out")
    bad("out-onto-csv", [*M, *C, "--csv", "feats.csv", "--out", "feats.csv"], "--out")
    bad("out-nodir", [*M, *C, *F, "--out", "nodir/r.json"], "--out")
    bad("sensor-other", [*M, *C, *F, "--sensor", "sensor.toml"], "--sensor")
    bad("sensor-bad", [*M, *C, *F, "--sensor", "s.toml"], "--sensor", setup=w("s.toml", BAD_TOMLS["layers-empty"]))
    bad("images-corrupt", [*I, *C, "--images", "c.png", "--background", "frames/*background*"], "c.png", setup=w("c.png", os.urandom(500)))  # fmt: skip
    bad("images-no-background", [*I, *C, "--images", "frames/*_f00*.png"], "--background")
    bad("background-without-images", [*M, *C, *F, "--background", "frames/*background*"], "--background")
    ok = "ok"
    c.append(Case("infer/ok-features", g, ["camera", "infer", *M, *C, *F, "--json"], ok, check=json_stdout))
    c.append(Case("infer/ok-csv-out", g, ["camera", "infer", *M, *C, "--csv", "feats.csv", "--out", "ré.json"], ok, check=has("ré.json")))  # fmt: skip
    c.append(Case("infer/ok-femimage", g, ["camera", "infer", *I, "--fem-image", "img.npy"], ok))
    c.append(Case("infer/ok-refine", g, ["camera", "infer", *I, "--fem-image", "img.npy", "--refine", *T, "--refine-correct", "none"], ok, timeout=300))  # fmt: skip
    c.append(Case("infer/ok-images", g, ["camera", "infer", *I, *C, "--images", "frames/*_f00*.png", "--background", "frames/*background*"], ok))  # fmt: skip
    return c


def gap_cases() -> list[Case]:
    c: list[Case] = []
    sy = ["gap", "synth", "--backend", "toy", "--n", "4", "--frames", "2", "--cache", "none"]

    def synth(cid: str, args: list[str], *names: str, out: str = "g2", expect: str = "refuse", **kw) -> None:
        c.append(Case(f"gap-synth/{cid}", "gap synth", [*sy, "--out", out, *args], expect, names, **kw))

    synth("out-existing", [], "--out", "--overwrite", out="meas")
    synth("overwrite-user-file", ["--overwrite"], "--out", "--overwrite", "notes.txt", out="meas", setup=w("meas/notes.txt", "mine\n"))  # fmt: skip
    synth("overwrite-foreign", ["--overwrite"], "--out", out="model")
    synth("overwrite-real", ["--overwrite"], "--out", out="meas", setup=edit_json("meas/measured.json", lambda d: d.__setitem__("synthetic", False)))  # fmt: skip
    synth("out-file", [], "--out", out="cal.json")
    for v in ["bogus=1", "background_E=nan", "background_E", "=", "background_E=1e308", "background_E=-5", "background_E=1,background_E=2"]:  # fmt: skip
        synth(f"effect={v!r}", ["--effect", v], "--effect")
    synth("phantoms-missing", ["--phantoms", "nosuch.csv"], "--phantoms")
    synth("phantoms-noE", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "id,d,h\nA,5,8\n"))
    synth("phantoms-dup", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "id,d,h,E\nA,5,8,40\nA,6,8,50\n"))  # fmt: skip
    synth("phantoms-slash", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "id,d,h,E\na/../../x,5,8,40\n"))  # fmt: skip
    synth("phantoms-nan", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "id,d,h,E\nA,nan,8,40\n"))
    synth("phantoms-empty", ["--phantoms", "p.csv"], "--phantoms", "p.csv", setup=w("p.csv", "id,d,h,E\n"))
    for v in ["0", "-1", "99999999999999999999"]:
        synth(f"n={v}", ["--n", v], "--n")
    for v in ["0", "99999999999999999999"]:
        synth(f"frames={v}", ["--frames", v], "--frames")
    for v in ["-1", "nan"]:
        synth(f"noise-scale={v}", ["--noise-scale", v], "--noise-scale")
    synth("seed-huge", ["--seed", "99999999999999999999999"], "--seed")
    synth("format", ["--format", "xls"], "--format")
    for v in ["-1", "nan", "inf"]:
        synth(f"force-noise={v}", ["--force-noise", v], "--force-noise")
    synth("cache-file", ["--cache", "cal.json"], "--cache")
    synth("jobs-0", ["--jobs", "0"], "--jobs")
    synth("jobs-huge", ["--jobs", "99999"], "--jobs")
    synth("mesh", ["--mesh", "x"], "--mesh")
    synth("interface", ["--interface", "x"], "--interface")
    synth("backend", ["--backend", "x"], "--backend")
    synth("sensor-bad", ["--sensor", "s.toml"], "--sensor", setup=w("s.toml", BAD_TOMLS["tissue-nan"]))
    synth("ok-parquet", ["--format", "parquet"], expect="ok", check=has("g2"))
    synth("ok-no-effect", ["--effect", ""], out="gé ø", expect="ok", check=has("gé ø/measured.json"))
    synth("ok-overwrite", ["--overwrite"], out="meas", expect="ok", check=has("meas/measured.json"))
    synth("edge-seed-neg", ["--seed", "-1"], "--seed", expect="either")

    di = ["gap", "diagnose", "--backend", "toy", *T, "--no-inverse", "--cache", "none"]

    def diag(cid: str, args: list[str], *names: str, out: str = "dg", expect: str = "refuse", meas: str = "meas", **kw) -> None:  # fmt: skip
        c.append(Case(f"gap-diagnose/{cid}", "gap diagnose", [*di, "--measured", meas, "--out", out, *args], expect, names, **kw))  # fmt: skip

    diag("measured-missing", [], "--measured", meas="nosuch")
    diag("measured-empty-dir", [], "--measured", meas="ed", setup=mkdir("ed"))
    diag("measured-csv-garbage", [], "--measured", "measured.csv", setup=w("meas/measured.csv", os.urandom(400)))
    diag("measured-json-garbage", [], "--measured", "measured.json", setup=w("meas/measured.json", "{"))
    diag("measured-json-list", [], "--measured", "measured.json", setup=w("meas/measured.json", "[]"))
    diag("difference-dotdot", [], "--allow-outside", setup=seq(meas_csv(_set_col("difference", 1, "../img.npy"))))
    diag("difference-abs", [], "--allow-outside", setup=meas_csv(_set_col("difference", 1, "/etc/passwd")))
    diag("difference-missing", [], "--measured", "nosuch.npy", setup=meas_csv(_set_col("difference", 1, "nosuch.npy")))
    diag("difference-garbage", [], "--measured", "g.npy", setup=seq(w("meas/g.npy", os.urandom(300)), meas_csv(_set_col("difference", 1, "g.npy"))))  # fmt: skip
    diag("difference-pickle", [], "--measured", "p.npy", setup=seq(npy("meas/p.npy", lambda: __import__("numpy").array([{"a": 1}], dtype=object), allow_pickle=True), meas_csv(_set_col("difference", 1, "p.npy"))))  # fmt: skip
    diag("dup-ids", [], "--measured", "P01", setup=meas_csv(_set_col("id", 2, "P01")))
    diag("id-slash", [], "--measured", "id", setup=meas_csv(_set_col("id", 2, "a/b")))
    diag("nan-O1", [], "--measured", "O1", setup=meas_csv(_set_col("O1", 1, "nan")))
    diag("text-d", [], "--measured", "d", setup=meas_csv(_set_col("d", 1, "big")))
    diag("neg-se", [], "--measured", "O2_se", setup=meas_csv(_set_col("O2_se", 1, "-1")))
    diag("no-O3", [], "--measured", "O3", setup=meas_csv(lambda rows: [r.pop(rows[0].index("O3")) for r in rows[::-1]]))
    diag("out-is-measured", [], "--out", out="meas")
    diag("out-foreign", [], "--out", out="model")
    diag("out-file", [], "--out", out="cal.json")
    diag("effects-bogus", ["--effects", "bogus"], "--effects")
    diag("effects-empty", ["--effects", ""], "--effects")
    diag("mesh", ["--mesh", "x"], "--mesh")
    diag("error-mesh", ["--error-mesh", "x"], "--error-mesh")
    diag("error-mesh-coarser", ["--error-mesh", "tiny"], "--error-mesh")
    for v in ["0", "-1", "99999999999999999999"]:
        diag(f"n-train={v}", ["--n-train", v], "--n-train")
    for v in ["-1", "nan"]:
        diag(f"model-floor={v}", ["--error-mesh", "none", "--model-floor", v], "--model-floor")
    for v in ["0", "1", "nan", "2"]:
        diag(f"alpha={v}", ["--alpha", v], "--alpha")
    diag("seed-huge", ["--seed", "99999999999999999999999"], "--seed")
    diag("cache-file", ["--cache", "cal.json"], "--cache")
    diag("jobs-0", ["--jobs", "0"], "--jobs")
    diag("sensor-bad", ["--sensor", "s.toml"], "--sensor", setup=w("s.toml", BAD_TOMLS["footprint-0"]))
    diag("ok", ["--error-mesh", "none"], expect="ok", check=has("dg/report.md", "dg/diagnosis.json"))
    diag("ok-json-unicode", ["--error-mesh", "none", "--json"], out="dé ø", expect="ok", check=json_stdout)

    ge = ["gap", "bench", *T]
    for cid, args, name in [
        ("n=0", ["--n", "0"], "--n"),
        ("n=-1", ["--n", "-1"], "--n"),
        ("n-huge", ["--n", "99999999999999999999"], "--n"),
        ("jobs=0", ["--jobs", "0"], "--jobs"),
        ("effect", ["--effect", "bogus=1"], "--effect"),
        ("data-mesh", ["--data-mesh", "x"], "--data-mesh"),
        ("data-interface", ["--data-interface", "x"], "--data-interface"),
        ("out-dir", ["--out", "sw"], "--out"),
        ("out-nodir", ["--out", "nodir/b.json"], "--out"),
        ("data-cache-file", ["--data-cache", "cal.json"], "--data-cache"),
    ]:
        c.append(Case(f"gap-bench/{cid}", "gap bench", [*ge, *args], "refuse", (name,)))

    st = ["gap", "selftest", "--backend", "toy", "--cache", "none", "--n-phantoms", "4", "--frames", "2"]
    for cid, args, name in [
        ("trials=0", ["--trials", "0"], "--trials"),
        ("trials=-1", ["--trials", "-1"], "--trials"),
        ("trials-huge", ["--trials", "99999999999999999999"], "--trials"),
        ("n-phantoms=0", ["--n-phantoms", "0"], "--n-phantoms"),
        ("n-phantoms=-1", ["--n-phantoms", "-1"], "--n-phantoms"),
        ("frames=0", ["--frames", "0"], "--frames"),
        ("start=-1", ["--start", "-1"], "--start"),
        ("start>trials", ["--trials", "2", "--start", "5"], "--start"),
        ("outside-bogus", ["--outside", "bogus"], "--outside"),
        ("effects-bogus", ["--effects", "bogus"], "--effects"),
        ("mesh", ["--mesh", "x"], "--mesh"),
        ("data-mesh", ["--data-mesh", "x"], "--data-mesh"),
        ("error-mesh", ["--error-mesh", "x"], "--error-mesh"),
        ("data-sizing", ["--data-sizing", "x"], "--data-sizing"),
        ("out-file", ["--out", "cal.json"], "--out"),
        ("out-foreign", ["--trials", "1", "--out", "model"], "--out"),
        ("seed-huge", ["--seed", "99999999999999999999999"], "--seed"),
        ("phantom-seed-huge", ["--phantom-seed", "99999999999999999999999"], "--phantom-seed"),
    ]:
        c.append(Case(f"gap-selftest/{cid}", "gap selftest", [*st, *args], "refuse", (name,)))
    c.append(Case("gap-selftest/ok", "gap selftest", [*st, "--trials", "1", "--error-mesh", "none", "--out", "stt"], "ok", check=has("stt/selftest.json"), timeout=300))  # fmt: skip
    c.append(Case("gap-effects/ok", "gap effects", ["gap", "effects"], "ok"))
    c.append(Case("gap-effects/extra", "gap effects", ["gap", "effects", "x"], "refuse", ("x",)))
    return c


def misc_cases() -> list[Case]:
    c: list[Case] = []
    de = ["demo", *T, "--jobs", "1"]

    def demo(cid: str, args: list[str], *names: str, expect: str = "refuse", **kw) -> None:
        c.append(Case(f"demo/{cid}", "demo", [*de, *args], expect, names, **kw))

    for v in ["0", "-1", "99999999999999999999"]:
        demo(f"n={v}", ["--n", v, "--out", "dm"], "--n")
    for v in ["0", "99999"]:
        demo(f"jobs={v}", ["--out", "dm", "--jobs", v], "--jobs")
    demo("mesh", ["--out", "dm", "--mesh", "x"], "--mesh")
    demo("out-sweep", ["--out", "sw"], "--out")
    demo("out-file", ["--out", "cal.json"], "--out")
    demo("out-train", ["--out", "model"], "--out")
    demo("out-empty", ["--out", ""], "--out")
    demo("sensor-bad", ["--out", "dm", "--sensor", "s.toml"], "--sensor", setup=w("s.toml", BAD_TOMLS["layer-zero-t"]))
    demo("sensor-missing", ["--out", "dm", "--sensor", "nosuch.toml"], "--sensor")
    demo("edge-n=4", ["--out", "dé mo", "--n", "4"], "--n", expect="either", check=has("dé mo"), timeout=400)

    st = ["study"]
    for cid, args, name in [
        ("unknown", ["bogus"], "bogus"),
        ("image-model-data-missing", ["image_model", "--data", "nosuch", "--out", "im"], "--data"),
        ("image-model-k0", ["image_model", "--data", "sw", "--k", "0", "--out", "im"], "--k"),
        ("image-model-hidden", ["image_model", "--data", "sw", "--hidden", "a", "--out", "im"], "--hidden"),
        ("image-model-validate", ["image_model", "--data", "sw", "--validate", "bogus", "--out", "im"], "--validate"),
        ("image-model-algo", ["image_model", "--data", "sw", "--algo", "adam", "--out", "im"], "--algo"),
        ("image-model-repeats", ["image_model", "--data", "sw", "--repeats", "0", "--out", "im"], "--repeats"),
        ("image-model-noise", ["image_model", "--data", "sw", "--image-noise", "nan", "--out", "im"], "--image-noise"),
        (
            "image-model-out-data",
            [
                "image_model",
                "--data",
                "sw",
                "--validate",
                "none",
                "--k",
                "3",
                "--hidden",
                "3",
                "--repeats",
                "1",
                "--epochs",
                "2",
                "--save-model",
                "sw",
            ],
            "--save-model",
        ),  # fmt: skip
        ("image-model-no-images", ["image_model", "--data", "samples.csv", "--out", "im"], "--data"),
    ]:
        c.append(Case(f"study/{cid}", "study", [*st, *args], "refuse", (name,)))
    c.append(Case("top/unknown-command", "elastimap", ["bogus"], "refuse", ("bogus",)))
    c.append(Case("top/version", "elastimap", ["--version"], "ok"))
    return c


def all_cases() -> list[Case]:
    return solve_cases() + sweep_cases() + dataset_cases() + train_cases() + camera_cases() + infer_cases() + gap_cases() + misc_cases()  # fmt: skip


# ----------------------------------------------------------------------------- fault scenarios


@dataclass
class Fault:
    cid: str
    fn: Callable[[Path, Path], str | None]  # (fixtures, scratch) -> failure reason or None
    needs_root: bool = False
    notes: list[str] = field(default_factory=list)


def _popen(args: list[str], work: Path) -> subprocess.Popen:
    home = work.parent / ".home"
    (home / "tmp").mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(
        [str(BIN), *args],
        cwd=work,
        env=_env(home),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        errors="replace",
        start_new_session=True,
    )


def _sweep_ids(folder: Path) -> list:
    import pyarrow.parquet as pq

    files = sorted(folder.glob("*.parquet"))
    if not files:
        return []
    return pq.read_table([str(p) for p in files]).column("sample_id").to_pylist()


def _wait_rows(folder: Path, n: int, p: subprocess.Popen, limit: float = 120.0) -> bool:
    t = time.monotonic()
    while time.monotonic() - t < limit and p.poll() is None:
        try:
            if len(_sweep_ids(folder)) >= n:
                return True
        except Exception:  # noqa: BLE001 - a file being written
            pass
        time.sleep(0.3)
    return False


def _signal_sweep(sig: int, expect_rc: int | None) -> Callable[[Path, Path], str | None]:
    def fn(fx: Path, work: Path) -> str | None:
        args = ["sweep", "run", *T, "--n", "12", "--jobs", "1", "--out", "sig", "--no-progress", "--batch-rows", "2"]
        p = _popen(args, work)
        if not _wait_rows(work / "sig", 1, p):
            p.kill()
            return "no row landed before the signal"
        os.killpg(p.pid, sig) if sig == signal.SIGKILL else p.send_signal(sig)
        try:
            out, err = p.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            return f"still running 120 s after signal {sig}"
        why = []
        if "Traceback" in out + err:
            why.append("traceback")
        if expect_rc is not None:
            if p.returncode != expect_rc:
                why.append(f"exit {p.returncode} (expected {expect_rc})")
            if "sweep:" not in out + err:
                why.append("no summary")
            left = [x.name for x in (work / "sig").iterdir() if "lock" in x.name or ".attempts" in x.name]
            if left:
                why.append(f"left {left}")
        ids_before = _sweep_ids(work / "sig")
        if len(ids_before) != len(set(ids_before)):
            why.append("duplicate rows after the signal")
        time.sleep(1)
        r = run_cli(args, work, 300)
        if r.rc != 0 and "--break-lock" in r.err and sig == signal.SIGKILL:
            r = run_cli([*args, "--break-lock"], work, 300)
        if r.rc != 0:
            why.append(f"resume exit {r.rc}: {_last(r.err)}")
        ids = _sweep_ids(work / "sig")
        if len(ids) != 12 or len(set(ids)) != 12:
            why.append(f"after resume {len(ids)} rows, {len(set(ids))} distinct (expected 12)")
        if not set(ids_before) <= set(ids):
            why.append("rows landed before the signal were lost")
        return "; ".join(why) or None

    return fn


@contextlib.contextmanager
def tmpfs(path: Path, size_kb: int, ro: bool = False):
    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k,mode=0755", "tmpfs", str(path)], check=True)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def _fill(path: Path) -> None:
    """Fill the file system at ``path`` to the last byte."""
    with open(path / ".filler", "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass
    with contextlib.suppress(OSError):
        for i in range(64):
            (path / f".f{i}").write_bytes(b"\0" * 64)


def _remount_ro(path: Path) -> None:
    subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True)


def _full_disk(args_of: Callable[[Path], list[str]], before: Callable[[Path, Path], None], after: Callable[[Path, Path, Result], str | None], size_kb: int = 2048, allow_left: bool = False) -> Callable[[Path, Path], str | None]:  # fmt: skip
    def fn(fx: Path, work: Path) -> str | None:
        with tmpfs(work.parent / "disk", size_kb) as disk:
            before(work, disk)
            _fill(disk)
            snap = snapshot(disk)
            r = run_cli(args_of(disk), work, 300)
            why = []
            if "Traceback" in r.out + r.err:
                why.append("traceback")
            if r.rc == 0:
                why.append("exit 0 on a full disk")
            lines = [ln for ln in r.err.splitlines() if ln.strip()]
            if not lines or not lines[-1].startswith("error"):
                why.append("no error line")
            now = snapshot(disk)
            changed = {k for k in set(snap) | set(now) if snap.get(k) != now.get(k)} - {".filler"}
            res = after(work, disk, r)
            if res:
                why.append(res)
            if changed and not res and not allow_left:
                why.append(f"left {sorted(changed)[:3]} on the full disk")
            return "; ".join(why) + (" | " + _last(r.err) if why else "") or None

    return fn


def _same_file(rel: str, keep: dict) -> Callable[[Path, Path, Result], str | None]:
    def after(work: Path, disk: Path, r: Result) -> str | None:
        p = disk / rel
        if not p.exists():
            return f"existing {rel} deleted"
        if p.read_bytes() != keep[rel]:
            return f"existing {rel} changed ({p.stat().st_size} bytes)"
        return None

    return after


def _full_calibrate() -> Callable[[Path, Path], str | None]:
    keep: dict = {}

    def before(work: Path, disk: Path) -> None:
        keep["cal.json"] = (work / "cal.json").read_bytes()
        shutil.copy(work / "cal.json", disk / "cal.json")

    return _full_disk(lambda d: ["camera", "calibrate", *T, "--frames", "2", "--fem-features", "sw", "--out", str(d / "cal.json"), "--plot", "cal.png"], before, _same_file("cal.json", keep))  # fmt: skip


def _full_export() -> Callable[[Path, Path], str | None]:
    keep: dict = {}

    def before(work: Path, disk: Path) -> None:
        b = b"id,x\n" + b"1,2\n" * 300
        keep["x.csv"] = b
        (disk / "x.csv").write_bytes(b)

    return _full_disk(
        lambda d: ["dataset", "export", "sw", "--out", str(d / "x.csv")], before, _same_file("x.csv", keep)
    )


def _full_train() -> Callable[[Path, Path], str | None]:
    def after(work: Path, disk: Path, r: Result) -> str | None:
        m = re.search(r"(/\S+)", _last(r.err).split("error:")[-1])
        tmpdir = work.parent / ".home" / "tmp"
        kept = [p for p in tmpdir.rglob("run.json")]
        if not kept:
            return "the finished run was discarded (no fallback copy with run.json)"
        return None if m or kept else "fallback not named"

    return _full_disk(lambda d: ["train", "--synthetic", "30", "--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress", "--workers", "1", "--out", str(d / "run")], lambda w, d: None, after)  # fmt: skip


def _full_diagnose() -> Callable[[Path, Path], str | None]:
    keep: dict = {}

    def before(work: Path, disk: Path) -> None:
        r = run_cli(["gap", "diagnose", "--backend", "toy", *T, "--no-inverse", "--cache", "none", "--error-mesh", "none", "--measured", "meas", "--out", str(disk / "dg")], work)  # fmt: skip
        assert r.rc == 0, r.err
        keep.update({str(p.relative_to(disk)): p.read_bytes() for p in (disk / "dg").rglob("*") if p.is_file()})

    def after(work: Path, disk: Path, r: Result) -> str | None:
        now = {str(p.relative_to(disk)): p.read_bytes() for p in (disk / "dg").rglob("*") if p.is_file()} if (disk / "dg").exists() else {}  # fmt: skip
        return None if now == keep else "the earlier report was changed or lost"

    return _full_disk(lambda d: ["gap", "diagnose", "--backend", "toy", *T, "--no-inverse", "--cache", "none", "--error-mesh", "none", "--measured", "meas", "--out", str(d / "dg"), "--seed", "3"], before, after, 8192)  # fmt: skip


def _full_synth() -> Callable[[Path, Path], str | None]:
    def after(work: Path, disk: Path, r: Result) -> str | None:
        return "a partial measured set was left" if (disk / "g").exists() else None

    return _full_disk(lambda d: ["gap", "synth", "--backend", "toy", "--n", "4", "--frames", "2", "--cache", "none", "--out", str(d / "g")], lambda w, d: None, after)  # fmt: skip


def _full_sweep() -> Callable[[Path, Path], str | None]:
    """The sweep may keep what landed; once space is freed the same command resumes and completes."""
    args_of = lambda d: ["sweep", "run", *T, "--n", "2", "--jobs", "1", "--no-progress", "--out", str(d / "s")]  # noqa: E731

    def after(work: Path, disk: Path, r: Result) -> str | None:
        for p in disk.glob(".f*"):
            p.unlink()
        r2 = run_cli(args_of(disk), work, 300)
        if r2.rc != 0:
            return f"rerun after freeing space: exit {r2.rc}: {_last(r2.err)}"
        ids = _sweep_ids(disk / "s")
        return None if len(ids) == 2 == len(set(ids)) else f"after the rerun {len(ids)} rows"

    # 2 MiB: the completed two-row sweep must fit once the filler is gone (64 KiB could not hold it)
    return _full_disk(args_of, lambda w, d: None, after, 2048, allow_left=True)


def _readonly(args_of: Callable[[Path], list[str]], names: tuple[str, ...], before: Callable[[Path, Path], None] | None = None) -> Callable[[Path, Path], str | None]:  # fmt: skip
    def fn(fx: Path, work: Path) -> str | None:
        with tmpfs(work.parent / "ro", 4096) as ro:
            if before:
                before(work, ro)
            _remount_ro(ro)
            snap = snapshot(ro)
            r = run_cli(args_of(ro), work, 300)
            lines = [ln for ln in r.err.splitlines() if ln.strip()]
            why = []
            if "Traceback" in r.out + r.err:
                why.append("traceback")
            if r.rc != 2:
                why.append(f"exit {r.rc}")
            if len(lines) != 1 or not any(n in lines[0] for n in names):
                why.append(f"{len(lines)} stderr lines / does not name {names}")
            if snapshot(ro) != snap:
                why.append("changed the read-only folder")
            return "; ".join(why) + (" | " + _last(r.err) if why else "") or None

    return fn


def _kill_diagnose() -> Callable[[Path, Path], str | None]:
    args_first = ["gap", "diagnose", "--backend", "toy", *T, "--no-inverse", "--cache", "none", "--error-mesh", "none", "--measured", "meas", "--out", "dg"]  # fmt: skip
    keep: dict = {}

    def fn(fx: Path, work: Path) -> str | None:
        r = run_cli(args_first, work)
        if r.rc != 0:
            return f"first diagnosis failed: {_last(r.err)}"
        keep.update({str(p.relative_to(work / "dg")): p.read_bytes() for p in (work / "dg").rglob("*") if p.is_file()})
        results = []
        for delay in (1.5, 3.0, 4.5):
            p = _popen([*args_first, "--seed", "7"], work)
            time.sleep(delay)
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            now = {str(q.relative_to(work / "dg")): q.read_bytes() for q in (work / "dg").rglob("*") if q.is_file()}
            if now != keep:
                # a complete new report is fine; a mix is not
                try:
                    seed = json.loads(now["diagnosis.json"]).get("seed", None)
                except Exception:  # noqa: BLE001
                    seed = "unreadable"
                if set(now) != set(keep) or seed not in (7, None):
                    results.append(f"kill at {delay} s left a mixed or partial report")
                else:
                    keep.clear()
                    keep.update(now)
        return "; ".join(results) or None

    return fn


def _concurrent_sweeps() -> Callable[[Path, Path], str | None]:
    def fn(fx: Path, work: Path) -> str | None:
        args = ["sweep", "run", *T, "--n", "4", "--jobs", "1", "--out", "cc", "--no-progress"]
        p = _popen(args, work)
        time.sleep(4)
        r = run_cli(args, work, 300)
        p.communicate(timeout=300)
        why = []
        if r.rc != 2 or "Traceback" in r.err:
            why.append(f"second sweep exit {r.rc}: {_last(r.err)}")
        ids = _sweep_ids(work / "cc")
        if len(ids) != 4 or len(set(ids)) != 4:
            why.append(f"{len(ids)} rows, {len(set(ids))} distinct")
        return "; ".join(why) or None

    return fn


def _train_overwrite_killed() -> Callable[[Path, Path], str | None]:
    """kill -9 of ``train --overwrite`` while it trains: the earlier run stays whole."""

    def fn(fx: Path, work: Path) -> str | None:
        keep = {str(p.relative_to(work / "model")): p.read_bytes() for p in (work / "model").rglob("*") if p.is_file()}
        args = ["train", "--synthetic", "200", "--repeats", "10", "--epochs", "3000", "--hidden", "8", "--no-progress",
                "--workers", "1", "--out", "model", "--overwrite"]  # fmt: skip
        p = _popen(args, work)
        time.sleep(12)
        if p.poll() is not None:
            return "finished before the kill (scenario not exercised)"
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        now = {str(q.relative_to(work / "model")): q.read_bytes() for q in (work / "model").rglob("*") if q.is_file()}
        return None if now == keep else "the earlier run was changed by a killed --overwrite"

    return fn


def all_faults() -> list[Fault]:
    return [
        Fault("fault/sweep-SIGTERM", _signal_sweep(signal.SIGTERM, 143)),
        Fault("fault/sweep-SIGINT", _signal_sweep(signal.SIGINT, 130)),
        Fault("fault/sweep-kill9", _signal_sweep(signal.SIGKILL, None)),
        Fault("fault/sweep-concurrent", _concurrent_sweeps()),
        Fault("fault/gap-diagnose-kill9", _kill_diagnose()),
        Fault("fault/train-overwrite-kill9", _train_overwrite_killed()),
        Fault("fault/full-calibrate", _full_calibrate(), True),
        Fault("fault/full-export", _full_export(), True),
        Fault("fault/full-train", _full_train(), True),
        Fault("fault/full-diagnose", _full_diagnose(), True),
        Fault("fault/full-synth", _full_synth(), True),
        Fault("fault/full-sweep", _full_sweep(), True),
        Fault(
            "fault/ro-compact",
            _readonly(
                lambda d: ["dataset", "compact", str(d / "sw")],
                ("sw", "read-only", "Read-only"),
                lambda w, d: shutil.copytree(w / "sw", d / "sw"),
            ),
            True,
        ),  # fmt: skip
        Fault(
            "fault/ro-train-out",
            _readonly(
                lambda d: [
                    "train",
                    "--synthetic",
                    "30",
                    "--repeats",
                    "1",
                    "--epochs",
                    "2",
                    "--hidden",
                    "3",
                    "--no-progress",
                    "--out",
                    str(d / "run"),
                ],
                ("--out",),
            ),
            True,
        ),  # fmt: skip
        Fault(
            "fault/ro-synth-out",
            _readonly(
                lambda d: [
                    "camera",
                    "synth",
                    *T,
                    "--d",
                    "8",
                    "--h",
                    "7",
                    "--E",
                    "50",
                    "--frames",
                    "1",
                    "--out",
                    str(d),
                ],
                ("--out",),
            ),
            True,
        ),  # fmt: skip
        Fault(
            "fault/ro-gap-cache",
            _readonly(
                lambda d: [
                    "gap",
                    "synth",
                    "--backend",
                    "toy",
                    "--n",
                    "4",
                    "--frames",
                    "2",
                    "--out",
                    "g",
                    "--cache",
                    str(d),
                ],
                ("--cache",),
            ),
            True,
        ),  # fmt: skip
        Fault(
            "fault/ro-export",
            _readonly(lambda d: ["dataset", "export", "sw", "--out", str(d / "x.csv")], ("--out",)),
            True,
        ),  # fmt: skip
    ]


# ----------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="run only cases whose id or command matches this regex")
    ap.add_argument("--keep", action="store_true", help="keep the scratch folder")
    ap.add_argument("--fixtures", type=Path, help="reuse (or build) the fixture folder here")
    ap.add_argument("--no-faults", action="store_true", help="skip the fault scenarios")
    ap.add_argument("--list", action="store_true", help="list the case ids and exit")
    a = ap.parse_args(argv)
    pat = re.compile(a.only) if a.only else None
    cases = [x for x in all_cases() if not pat or pat.search(x.cid) or pat.search(x.group)]
    faults = [] if a.no_faults else [f for f in all_faults() if not pat or pat.search(f.cid)]
    if a.list:
        print("\n".join([x.cid for x in cases] + [f.cid for f in faults]))
        return 0
    ids = [x.cid for x in all_cases()]
    assert len(ids) == len(set(ids)), "duplicate case ids"
    scratch = Path(tempfile.mkdtemp(prefix="badsweep-"))
    fx = a.fixtures or scratch / "fixtures"
    t0 = time.monotonic()
    print(f"fixtures: {fx}", flush=True)
    build_fixtures(fx)
    print(f"fixtures ready in {time.monotonic() - t0:.0f} s; {len(cases)} cases, {len(faults)} faults", flush=True)
    per: dict[str, list[int]] = {}
    fails: list[str] = []
    tracebacks = 0
    for case in cases:
        work = prepare(fx, scratch / "cases", case.cid)
        if case.setup:
            case.setup(work)
        before = snapshot(work.parent)
        r = run_cli(case.args, work, case.timeout)
        changed = diff(before, snapshot(work.parent))
        good, why = judge(case, r, changed)
        tracebacks += "Traceback" in r.out + r.err
        st = per.setdefault(case.group, [0, 0, 0])
        st[0] += 1
        st[1] += good
        st[2] += "Traceback" in r.out + r.err
        if not good:
            fails.append(f"FAIL {case.cid} [{case.expect}] ({r.seconds:.1f} s): {why}")
            print(fails[-1], flush=True)
        if not a.keep:
            shutil.rmtree(work.parent, ignore_errors=True)
    fault_res: list[tuple[str, str]] = []
    root = os.geteuid() == 0
    for f in faults:
        if f.needs_root and not root:
            fault_res.append((f.cid, "SKIPPED (needs root for the mounts)"))
            continue
        work = prepare(fx, scratch / "faults", f.cid)
        try:
            why = f.fn(fx, work)
        except Exception as e:  # noqa: BLE001 - a broken scenario is a failed one, reported
            why = f"scenario error: {type(e).__name__}: {e}"
        fault_res.append((f.cid, why or "ok"))
        print(f"{f.cid}: {why or 'ok'}", flush=True)
        if not a.keep:
            shutil.rmtree(work.parent, ignore_errors=True)
    n = sum(v[0] for v in per.values())
    clean = sum(v[1] for v in per.values())
    print("\n== bad-input sweep (fresh), per command: cases, clean, tracebacks")
    for grp, (k, good, tb) in sorted(per.items()):
        print(f"  {grp:18s} {k:4d} {good:4d} {tb:3d}")
    if n:
        print(f"TOTAL {n} cases: {clean} clean ({100.0 * clean / n:.1f} %), {tracebacks} tracebacks")
    for line in fails:
        print(line)
    if fault_res:
        passed = sum(1 for _, why in fault_res if why == "ok")
        skipped = sum(1 for _, why in fault_res if why.startswith("SKIPPED"))
        print(f"FAULTS {len(fault_res)}: {passed} lost nothing and behaved, {skipped} skipped")
        for cid, why in fault_res:
            if why != "ok":
                print(f"FAULT {cid}: {why}")
    print(f"wall {time.monotonic() - t0:.0f} s")
    if a.keep:
        print(f"scratch kept: {scratch}")
    else:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0 if clean == n and all(why == "ok" or why.startswith("SKIPPED") for _, why in fault_res) else 1


if __name__ == "__main__":
    sys.exit(main())

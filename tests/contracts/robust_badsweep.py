"""A sweep of bad and edge inputs across every command, written for issue 40 (not collected by pytest).

    .venv/bin/python tests/robust_badsweep.py [--only WORD] [--json out.json]

Each case runs the console script in a forked child of this process (the imports are paid once),
in a fresh working folder, with a time limit; a case whose checks come too late runs into the limit
or leaves files.  A case is *clean* when it exits 2 with one line on stderr naming one of its
expected words, no traceback, and nothing written (``refuse`` cases), or when it succeeds without
a traceback (``edge`` cases, which may also be refused cleanly).  Everything else is counted by
what went wrong: traceback, accepted (exit 0 where a refusal was due), several lines, wrong name,
files left, time limit.  Inputs are SYNTHETIC (analytic sample rows, the toy gap backend).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_bad_inputs import invoke, make_calibration, make_dataset, make_model, snapshot  # noqa: E402

HUGE = "99999999999999999999"
GSYN = ["--backend", "toy", "--cache", "none", "--n", "4", "--frames", "2", "--mesh", "tiny"]
TRAIN = ["--synthetic", "30", "--repeats", "1", "--epochs", "2", "--hidden", "3", "--out", "tr"]
SOLVE = ["--d", "8", "--h", "8", "--E", "60", "--mesh", "tiny"]
CSYN = ["--d", "8", "--h", "8", "--E", "60", "--mesh", "tiny", "--frames", "2", "--out", "fr"]
INF = ["--model", "{A}/model", "--calibration", "{A}/cal.json", "--identifiability", "none"]
SWEEP = ["run", "--solver", "synthetic", "--mesh", "tiny", "--n", "2", "--jobs", "1", "--no-progress", "--out", "sw"]
DIAG = ["diagnose", "--backend", "toy", "--cache", "none", "--no-inverse", "--out", "dg"]


def cases() -> list[tuple[str, str, list[str], tuple[str, ...]]]:
    """(kind, script, args, words the error line must name one of); ``{A}`` = the assets folder."""
    R, E = "refuse", "edge"
    c = []
    # solve
    for flag, vals in {
        "--d": ["0", "-3", "nan", "1e-300", "1e308", "abc"],
        "--E": ["0", "-1", "1e308", "inf", "1e-300"],
        "--h": ["0", "100", "nan", "-2"],
        "--delta": ["1e9", "-1", "0"],
        "--force": ["0", "-5", "inf"],
        "--pixel": ["0", "1e-9", "nan"],
        "--thickness": ["0", "1e9", "-1"],
        "--layers": ["x", "1:", "100:5", "1:0", "1:nan"],
    }.items():
        c += [(R, "solve", [*SOLVE, flag, v], (flag,)) for v in vals]
    c += [
        (R, "solve", [*SOLVE, "--mesh", "huge"], ("--mesh",)),
        (R, "solve", [*SOLVE, "--interface", "glue"], ("--interface",)),
        (R, "solve", [*SOLVE, "--image", "/nonexistent/a.png"], ("--image",)),
        (R, "solve", [*SOLVE, "--image", "{A}"], ("--image",)),
        (R, "solve", [*SOLVE, "--image", "{A}/loop.png"], ("--image",)),
        (R, "solve", [*SOLVE, "--image-npy", "x.txt"], ("--image-npy",)),
        (R, "solve", [*SOLVE, "--vtx", "{A}/a-file"], ("--vtx",)),
        (R, "solve", [*SOLVE, "--degree", "3"], ("--degree",)),
    ]
    # sweep
    for flag, vals in {
        "--n": ["-1", "1.5", HUGE],
        "--jobs": ["0", "99999", HUGE],
        "--seed": ["-5", HUGE],
        "--mesh": ["foo"],
        "--design": ["grid"],
        "--ranges": ["d=5:2", "d=a:b", "q=1:2", "d=1:2:cube", "E=0:10:log", "d=1:nan"],
        "--samples": ["{A}/missing.csv", "{A}/empty.csv", "{A}/notes.txt", "{A}/nan-samples.csv"],
        "--batch-rows": ["0", HUGE],
        "--timeout": ["-1", "nan"],
        "--out": ["{A}/a-file", "{A}/run"],
        "--scheduler": ["", "nowhere"],
        "--connect-timeout": ["0", "-1"],
        "--worker-wait": ["-1", "inf"],
    }.items():
        c += [(R, "sweep", [*SWEEP, flag, v], (flag, "--samples")) for v in vals]
    c += [
        (R, "sweep", ["bench", "--out", "{A}/a-file"], ("--out",)),
        (R, "sweep", ["bench", "--n", "-1"], ("--n",)),
    ]
    # dataset
    c += [
        (R, "dataset", ["inspect", "{A}/missing"], ("path", "missing")),
        (R, "dataset", ["inspect", "{A}/notes.txt"], ("notes.txt",)),
        (R, "dataset", ["inspect", "{A}/foreign.parquet"], ("foreign",)),
        (R, "dataset", ["inspect", "{A}/ds", "--top", "-1"], ("--top",)),
        (R, "dataset", ["inspect", "{A}/ds", "--top", HUGE], ("--top",)),
        (R, "dataset", ["plot", "{A}/ds", "--out", "{A}/a-file"], ("--out",)),
        (R, "dataset", ["plot", "{A}/ds", "--out", "p", "--images", "0"], ("--images",)),
        (R, "dataset", ["plot", "{A}/ds", "--out", "p", "--images", HUGE], ("--images",)),
        (R, "dataset", ["export", "{A}/ds", "--out", "{A}"], ("--csv", "--out")),
        (R, "dataset", ["export", "{A}/ds", "--out", "nodir/x.csv"], ("--csv", "--out")),
        (R, "dataset", ["compact", "{A}/notes.txt"], ("notes.txt", "path")),
        (R, "dataset", ["compact", "{A}/ds", "--batch-rows", "0"], ("--batch-rows",)),
        (R, "dataset", ["compact", "{A}/ds", "--batch-rows", HUGE], ("--batch-rows",)),
    ]
    # train
    for flag, vals in {
        "--epochs": ["0", HUGE],
        "--repeats": ["0", HUGE],
        "--hidden": ["0", "a", "3,-1", ""],
        "--feature-noise": ["2", "nan"],
        "--val-fraction": ["1", "-0.1"],
        "--test-split": ["0", "1.5"],
        "--threads": ["-1"],
        "--workers": ["-1", HUGE],
        "--algo": ["x"],
        "--validate": ["x"],
        "--activation": ["x"],
        "--device": ["tpu"],
        "--out": ["{A}/a-file", "{A}/run"],
        "--seed": ["-1"],
    }.items():
        c += [(R, "train", [*TRAIN, flag, v], (flag,)) for v in vals]
    c += [
        (R, "train", ["--data", "{A}/missing", "--out", "tr"], ("--data",)),
        (R, "train", ["--data", "{A}/notes.txt", "--out", "tr"], ("--data", "notes")),
        (R, "train", ["--data", "{A}/foreign.parquet", "--out", "tr"], ("--data", "foreign")),
        (R, "train", ["--out", "tr"], ("--data", "--synthetic")),
        (R, "train", ["--synthetic", "0", "--out", "tr"], ("--synthetic",)),
        (R, "train", ["--synthetic", HUGE, "--out", "tr"], ("--synthetic",)),
        (R, "train", ["--data", "{A}/ds", "--hidden", "3", "--out", "{A}/ds", "--overwrite"], ("--out",)),
        (R, "train", ["--data", "{A}/ds", "--hidden", "3", "--out", "{A}", "--overwrite"], ("--out",)),
    ]
    # camera synth / features / detect
    for flag, vals in {
        "--d": ["0", "nan"],
        "--frames": ["0", HUGE],
        "--seed": ["-1", HUGE],
        "--name": ["a/b", "", "..", "../x"],
        "--sensor": ["{A}/missing.json", "{A}/notjson.json", "{A}/sensor-list.json", "{A}/sensor-badkey.json"],
        "--out": ["{A}/a-file"],
        "--noise-scale": ["-1", "1e308"],
        "--binning": ["0", HUGE],
    }.items():
        c += [(R, "camera", ["synth", *CSYN, flag, v], (flag,)) for v in vals]
    c += [
        (R, "camera", ["features", "--images", "{A}/missing.png", "--background", "{A}/frames/b*.png"], ("--images",)),
        (
            R,
            "camera",
            ["features", "--images", "{A}/frames/l*.png", "--background", "{A}/nomatch*.png"],
            ("--background",),
        ),
        (R, "camera", ["features", "--images", "{A}/big.png", "--background", "{A}/frames/b*.png"], ("--images",)),
        (R, "camera", ["features", "--images", "{A}/notes.txt", "--background", "{A}/frames/b*.png"], ("--images",)),
        (R, "camera", ["detect", "--out", "dt", "--repeats", "0"], ("--repeats",)),
        (R, "camera", ["detect", "--out", "dt", "--repeats", HUGE], ("--repeats",)),
        (R, "camera", ["detect", "--out", "dt", "--noise-scales", "a"], ("--noise-scales",)),
        (R, "camera", ["detect", "--out", "dt", "--noise-scales", "inf"], ("--noise-scales",)),
        (R, "camera", ["detect", "--out", "{A}/a-file"], ("--out",)),
    ]
    # calibrate
    CAL = ["--mesh", "tiny", "--out", "cal.json"]
    c += [
        (R, "calibrate", [*CAL, "--frames", "0"], ("--frames",)),
        (R, "calibrate", [*CAL, "--frames", "1"], ("--frames",)),
        (R, "calibrate", [*CAL, "--frames", HUGE], ("--frames",)),
        (R, "calibrate", [*CAL, "--phantoms", "{A}/missing.csv"], ("--phantoms",)),
        (R, "calibrate", [*CAL, "--phantoms", "{A}/ph-dup.csv"], ("--phantoms",)),
        (R, "calibrate", [*CAL, "--phantoms", "{A}/ph-inf.csv"], ("--phantoms",)),
        (R, "calibrate", [*CAL, "--phantoms", "{A}/ph-slash.csv"], ("--phantoms",)),
        (R, "calibrate", [*CAL, "--fem-features", "{A}/empty.csv"], ("--fem-features",)),
        (R, "calibrate", [*CAL, "--fem-features", "{A}/fem-dupO3.csv"], ("--fem-features",)),
        (R, "calibrate", [*CAL, "--fem-features", "{A}/fem-text.csv"], ("--fem-features",)),
        (R, "calibrate", [*CAL, "--camera-csv", "{A}/cam-etc.csv", "--fem-features", "{A}/fem.csv"], ("--camera-csv",)),
        (R, "calibrate", [*CAL, "--camera-csv", "{A}/cam-up.csv", "--fem-features", "{A}/fem.csv"], ("--camera-csv",)),
        (R, "calibrate", ["--mesh", "tiny", "--out", "nodir/cal.json"], ("--out",)),
        (E, "calibrate", ["--fem-features", "{A}/fem.csv", "--out", "cal.json", "--frames", "2"], ()),
    ]
    # infer
    c += [
        (R, "infer", ["--model", "{A}/missing", "--features", "1", "2", "3"], ("--model",)),
        (R, "infer", ["--model", "{A}/notes.txt", "--features", "1", "2", "3"], ("--model",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--model", "{A}/model-nanrange"], ("--model",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--model", "{A}/model-minmax"], ("--model",)),
        (R, "infer", [*INF, "--features", "nan", "1", "2"], ("--features",)),
        (R, "infer", [*INF, "--features", "a", "b", "c"], ("--features",)),
        (R, "infer", [*INF, "--features", "1", "2"], ("--features",)),
        (R, "infer", [*INF[:2], "--calibration", "{A}/notjson.json", "--features", "1", "2", "3"], ("--calibration",)),
        (R, "infer", [*INF[:2], "--calibration", "{A}/cal-nan.json", "--features", "1", "2", "3"], ("--calibration",)),
        (
            R,
            "infer",
            [*INF[:2], "--calibration", "{A}/cal-settings.json", "--features", "1", "2", "3"],
            ("--calibration",),
        ),
        (R, "infer", [*INF, "--csv", "{A}/dup.csv"], ("--csv",)),
        (R, "infer", [*INF, "--csv", "{A}/dupO3.csv"], ("--csv",)),
        (R, "infer", [*INF, "--csv", "{A}/empty.csv"], ("--csv",)),
        (R, "infer", [*INF, "--csv", "{A}/frames-etc.csv"], ("--csv",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--threshold", "0"], ("--threshold",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--threshold", "nan"], ("--threshold",)),
        (R, "infer", [*INF[:4], "--identifiability", "", "--features", "1", "2", "3"], ("--identifiability",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--out", "nodir/x.csv"], ("--out",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--out", "{A}"], ("--out",)),
    ]
    # gap
    for flag, vals in {
        "--n": ["3", HUGE],
        "--frames": ["0", HUGE],
        "--seed": ["-1"],
        "--effect": ["nope=1", "friction=abc", "friction=inf"],
        "--noise-scale": ["-1", "1e308", "nan"],
        "--force-noise": ["0", "inf", "-0.1"],
        "--cache": ["{A}/a-file"],
        "--phantoms": ["{A}/missing.csv", "{A}/ph-slash.csv"],
        "--jobs": ["0", "99999"],
    }.items():
        c += [(R, "gap", ["synth", *GSYN, "--out", "gs", flag, v], (flag,)) for v in vals]
    c += [
        (R, "gap", ["synth", *GSYN, "--out", "{A}/a-file"], ("--out",)),
        (R, "gap", ["synth", *GSYN, "--out", "{A}/M", "--overwrite"], ("--out",)),
        (R, "gap", ["synth", *GSYN, "--out", "{A}/S-user", "--overwrite"], ("--out",)),
    ]
    for flag, vals in {
        "--jobs": ["0", HUGE],
        "--alpha": ["0.6", "nan", "0"],
        "--n-train": ["1", HUGE],
        "--effects": ["nope"],
        "--out": ["{A}/a-file"],
        "--error-mesh": ["foo"],
        "--model-floor": ["-1", "inf"],
        "--seed": ["-1"],
    }.items():
        c += [(R, "gap", [*DIAG, "--measured", "{A}/S", flag, v], (flag,)) for v in vals]
    for m in ("missing", "S-decoy", "S-up", "S-etc", "S-settings", "S-sidecar-list", "S-slash", "S-sensor"):
        c.append((R, "gap", [*DIAG, "--measured", "{A}/" + m], ("--measured",)))
    for flag, vals in {
        "--trials": ["0", HUGE],
        "--seed": ["-1"],
        "--n-phantoms": ["3"],
        "--frames": ["0"],
        "--out": ["{A}/a-file", "{A}/run"],
    }.items():
        c += [(R, "gap", ["selftest", "--backend", "toy", "--cache", "none", flag, v], (flag,)) for v in vals]
    # demo
    c += [
        (R, "elastimap", ["demo", "--n", "0"], ("--n",)),
        (R, "elastimap", ["demo", "--n", HUGE], ("--n",)),
        (R, "elastimap", ["demo", "--jobs", "0"], ("--jobs",)),
        (R, "elastimap", ["demo", "--jobs", "99999"], ("--jobs",)),
        (R, "elastimap", ["demo", "--out", "{A}/a-file"], ("--out",)),
        (R, "elastimap", ["demo", "--out", "{A}/ds"], ("--out",)),
        (R, "elastimap", ["demo", "--out", "{A}/demo-user"], ("--out",)),
        (R, "elastimap", ["demo", "--mesh", "x"], ("--mesh",)),
    ]
    return c


def fresh_cases() -> list[tuple[str, str, list[str], tuple[str, ...]]]:
    """A second set, written after the fixes and run once (a held-out check of the first set's fixes)."""
    R = "refuse"
    c = []
    for flag, vals in {
        "--h": ["1e308"],
        "--delta": ["nan"],
        "--thickness": ["inf"],
        "--pixel": ["1e308"],
        "--force": ["1e308"],
        "--image": [""],
        "--image-npy": ["{A}/nodir/x.npy"],
        "--layers": ["2:100,2:nan", "-1:5", "2:1e9"],
        "--interface": [""],
        "--nu": ["0.5", "nan"],
    }.items():
        c += [(R, "solve", [*SOLVE, flag, v], (flag,)) for v in vals]
    for flag, vals in {
        "--ranges": ["d=2:15,d=3:4", "E=-5:10", "h=1:inf"],
        "--samples": ["{A}/foreign.parquet", "{A}/samples-neg.csv", "{A}/samples-dupid.csv", "{A}"],
        "--seed": ["1.5"],
        "--timeout": ["inf"],
        "--connect-timeout": ["nan"],
        "--dashboard": ["abc"],
        "--out": ["{A}/notes.txt"],
    }.items():
        c += [(R, "sweep", [*SWEEP, flag, v], (flag, "--samples")) for v in vals]
    c += [
        (R, "dataset", ["inspect", "{A}/emptydir"], ("emptydir", "PATH")),
        (R, "dataset", ["plot", "{A}/ds", "--out", "{A}/notes.txt"], ("--out",)),
        (R, "dataset", ["export", "{A}/ds", "--out", "{A}/notes.txt/x.csv"], ("--csv", "--out")),
        (R, "dataset", ["compact", "{A}/foreign.parquet"], ("foreign", "PATH")),
        (R, "dataset", ["compact", "{A}/missing"], ("missing", "PATH")),
    ]
    for flag, vals in {
        "--hidden": ["25,10:foo", "1000000000"],
        "--activation": [""],
        "--test-split": ["nan"],
        "--epochs": ["-5"],
        "--seed": [HUGE],
        "--device": ["cuda:x"],
    }.items():
        c += [(R, "train", [*TRAIN, flag, v], (flag,)) for v in vals]
    c += [
        (R, "train", ["--data", "{A}/emptydir", "--out", "tr"], ("--data", "emptydir")),
        (R, "train", ["--data", "{A}/fem.csv", "--out", "tr"], ("--data", "fem.csv")),
    ]
    for flag, vals in {
        "--h": ["100"],
        "--E": ["0"],
        "--delta": ["nan"],
        "--tissue-E": ["-1"],
        "--bits": ["12"],
        "--binning": ["65"],
        "--format": ["bmp"],
        "--sensor": ["{A}", "{A}/sensor-seed.json", "{A}/sensor-type.json"],
    }.items():
        c += [(R, "camera", ["synth", *CSYN, flag, v], (flag,)) for v in vals]
    c += [
        (R, "camera", ["features", "--images", "{A}/frames", "--background", "{A}/frames/b*.png"], ("--images",)),
        (R, "camera", ["features", "--images", "{A}/empty.csv", "--background", "{A}/frames/b*.png"], ("--images",)),
        (
            R,
            "camera",
            ["features", "--images", "{A}/frames/l*.png", "--background", "{A}/frames16/*.png"],
            ("--background",),
        ),
    ]
    CAL = ["--mesh", "tiny", "--out", "cal.json"]
    c += [
        (R, "calibrate", [*CAL, "--phantoms", "{A}/ph-two.csv"], ("--phantoms",)),
        (R, "calibrate", [*CAL, "--phantoms", "{A}/notes.txt"], ("--phantoms",)),
        (R, "calibrate", [*CAL, "--delta", "0"], ("--delta",)),
        (R, "calibrate", [*CAL, "--write-frames", "{A}/notes.txt"], ("--write-frames",)),
        (R, "calibrate", [*CAL, "--plot", "{A}"], ("--plot",)),
        (R, "calibrate", [*CAL, "--fem-features", "{A}/foreign.parquet"], ("--fem-features",)),
        (R, "calibrate", [*CAL, "--camera-csv", "{A}/dup.csv", "--fem-features", "{A}/fem.csv"], ("--camera-csv",)),
    ]
    c += [
        (
            R,
            "infer",
            ["--model", "{A}/model", "--features", "1", "2", "3", "--identifiability", "none"],
            ("--calibration",),
        ),
        (R, "infer", [*INF, "--calibration", "{A}/missing.json", "--features", "1", "2", "3"], ("--calibration",)),
        (R, "infer", [*INF, "--csv", "{A}/missing.csv"], ("--csv",)),
        (R, "infer", [*INF, "--csv", "{A}/ids-slash.csv"], ("--csv",)),
        (R, "infer", [*INF, "--fem-image", "{A}/notes.txt"], ("--fem-image", "--model")),
        (R, "infer", [*INF, "--fem-image", "{A}/missing.npy"], ("--fem-image",)),
        (R, "infer", [*INF, "--features", "1", "2", "3", "--threshold", "inf"], ("--threshold",)),
        (R, "infer", [*INF, "--identifiability", "{A}/notes.txt", "--features", "1", "2", "3"], ("--identifiability",)),
    ]
    for flag, vals in {
        "--effect": ["friction=0.3,friction=0.4", "friction"],
        "--format": ["xls"],
        "--phantoms": ["{A}/ph-two.csv", "{A}/ph-neg.csv"],
        "--n": ["0"],
        "--interface": ["glue"],
    }.items():
        c += [(R, "gap", ["synth", *GSYN, "--out", "gs", flag, v], (flag,)) for v in vals]
    for flag, vals in {"--mesh": ["x"], "--n-train": ["0"], "--alpha": ["0.5"], "--error-mesh": ["huge"]}.items():
        c += [(R, "gap", [*DIAG, "--measured", "{A}/S", flag, v], (flag,)) for v in vals]
    for m in ("notes.txt", "emptydir", "S-tissueE", "S-version", "S-three", "S-shape"):
        c.append((R, "gap", [*DIAG, "--measured", "{A}/" + m], ("--measured",)))
    for flag, vals in {
        "--start": ["-1", "99"],
        "--outside": ["nope"],
        "--data-mesh": ["foo"],
        "--trials": ["-1"],
    }.items():
        c += [(R, "gap", ["selftest", "--backend", "toy", "--cache", "none", flag, v], (flag,)) for v in vals]
    c += [
        (R, "elastimap", ["demo", "--jobs", "-1"], ("--jobs",)),
        (R, "elastimap", ["demo", "--out", "{A}/notes.txt"], ("--out",)),
    ]
    return c


def build_fresh_assets(a: Path) -> None:
    import json as _json

    import numpy as np
    import pandas as pd

    (a / "emptydir").mkdir()
    (a / "samples-neg.csv").write_text("d,h,E\n-5,8,40\n6,8,40\n")
    (a / "samples-dupid.csv").write_text("sample_id,d,h,E\nx,5,8,40\nx,6,8,40\n")
    (a / "sensor-seed.json").write_text('{"seed": -3}')
    (a / "sensor-type.json").write_text('{"noise_scale": "x"}')
    pd.read_csv(a / "ph-ok.csv").iloc[:2].to_csv(a / "ph-two.csv", index=False)
    pd.read_csv(a / "ph-ok.csv").assign(d=-1.0).to_csv(a / "ph-neg.csv", index=False)
    (a / "ids-slash.csv").write_text("id,O1,O2,O3\na/b,1,2,3\n")
    from elastimap.camera.frames import write_frames

    rng = np.random.default_rng(1)
    write_frames(rng.integers(0, 60000, (2, 40, 40), dtype=np.uint16), a / "frames16", "b", synthetic=False)
    t = pd.read_csv(a / "S" / "measured.csv")
    for name, edit in (
        ("S-tissueE", lambda d: t.assign(tissue_E=-1.0).to_csv(d / "measured.csv", index=False)),
        ("S-three", lambda d: t.iloc[:3].to_csv(d / "measured.csv", index=False)),
        ("S-version", None),
        ("S-shape", None),
    ):
        shutil.copytree(a / "S", a / name)
        if edit:
            edit(a / name)
    side = _json.loads((a / "S" / "measured.json").read_text())
    side["version"] = 9
    (a / "S-version" / "measured.json").write_text(_json.dumps(side))
    f = t["difference"].iloc[0]
    np.save(a / "S-shape" / f, np.zeros((3, 3), np.float32))


def build_assets(a: Path) -> None:
    import numpy as np
    import pandas as pd

    make_dataset(a / "ds")
    pd.DataFrame({"x": [1.0, 2.0]}).to_parquet(a / "foreign.parquet")
    (a / "notes.txt").write_text("not data\n")
    (a / "a-file").write_text("a file\n")
    (a / "notjson.json").write_text("{ nope\n")
    (a / "empty.csv").write_text("")
    (a / "loop.png").symlink_to(a / "loop.png")
    (a / "nan-samples.csv").write_text("d,h,E\n5,8,nan\n6,8,40\n")
    (a / "sensor-list.json").write_text("[1, 2]\n")
    (a / "sensor-badkey.json").write_text('{"pixels": 3}\n')
    (a / "run").mkdir()
    (a / "run" / "results.csv").write_text("an earlier run\n")
    (a / "demo-user" / "train").mkdir(parents=True)
    (a / "demo-user" / "train" / "my-model.txt").write_text("the user's own\n")
    (a / "dup.csv").write_text("id,O1,O2,O3\nA,1,2,3\nA,1,2,3\n")
    (a / "dupO3.csv").write_text("id,O1,O2,O3,O3\nA,1,2,3,4\n")
    (a / "frames-etc.csv").write_text("id,images,background\nA,/etc/*,/etc/*\n")
    model = make_model(a / "model")
    for name, edit in {
        "nanrange": lambda d: d.update(feature_range=[[float("nan")] * 3, [1.0] * 3]),
        "minmax": lambda d: d.update(target_range=[[10.0, 10.0, 10.0], [1.0, 1.0, 1.0]]),
    }.items():
        shutil.copytree(model, a / f"model-{name}")
        mj = json.loads((model / "model.json").read_text())
        edit(mj)
        (a / f"model-{name}" / "model.json").write_text(json.dumps(mj))
    make_calibration(a / "cal.json")
    cal = json.loads((a / "cal.json").read_text())
    bad = json.loads(json.dumps(cal))
    bad["fits"]["O1"]["slope"] = float("nan")
    (a / "cal-nan.json").write_text(json.dumps(bad))
    bad = json.loads(json.dumps(cal))
    bad["feature_settings"] = [1]
    (a / "cal-settings.json").write_text(json.dumps(bad))
    ph = pd.read_csv(Path(__file__).resolve().parents[2] / "dataset" / "phantoms.csv", comment="#")
    ph.to_csv(a / "ph-ok.csv", index=False)
    pd.concat([ph, ph.iloc[:1]]).to_csv(a / "ph-dup.csv", index=False)
    ph.assign(E=[np.inf] + list(ph["E"][1:])).to_csv(a / "ph-inf.csv", index=False)
    ph.assign(name=["a/b"] + list(ph["name"][1:])).to_csv(a / "ph-slash.csv", index=False)
    fem = pd.DataFrame({"name": ph["name"], "O1": 1.0 + np.arange(len(ph)), "O2": 2.0, "O3": 3.0})
    fem["O2"] = fem["O1"] * 2
    fem["O3"] = fem["O1"] * 3
    fem.to_csv(a / "fem.csv", index=False)
    (a / "fem-dupO3.csv").write_text("name,O1,O2,O3,O3\n" + "".join(f"{n},1,2,3,4\n" for n in ph["name"]))
    (a / "fem-text.csv").write_text("name,O1,O2,O3\n" + "".join(f"{n},1,x,3\n" for n in ph["name"]))
    (a / "cam-etc.csv").write_text("name,images,background\n" + "".join(f"{n},/etc/*,/etc/*\n" for n in ph["name"]))
    (a / "cam-up.csv").write_text("name,images,background\n" + "".join(f"{n},../x.png,../y.png\n" for n in ph["name"]))
    # frames
    from elastimap.camera.frames import write_frames

    rng = np.random.default_rng(0)
    write_frames(rng.integers(0, 200, (2, 40, 40), dtype=np.uint8), a / "frames", "l", synthetic=False)
    write_frames(rng.integers(0, 200, (2, 40, 40), dtype=np.uint8), a / "frames", "b", synthetic=False)
    import struct
    import zlib

    def chunk(k, d):
        return struct.pack(">I", len(d)) + k + d + struct.pack(">I", zlib.crc32(k + d))

    (a / "big.png").write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", 100000, 100000, 8, 0, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
    )
    # measured sets
    r = invoke("gap", ["synth", *GSYN, "--out", str(a / "S")])
    assert r[0] == 0, r
    shutil.copytree(a / "S", a / "M")
    side = json.loads((a / "M" / "measured.json").read_text())
    side["synthetic"] = False
    (a / "M" / "measured.json").write_text(json.dumps(side))
    shutil.copytree(a / "S", a / "S-user")
    (a / "S-user" / "my-notes.txt").write_text("mine\n")
    np.save(a / "decoy.npy", np.zeros((100, 100)))
    table = pd.read_csv(a / "S" / "measured.csv")
    for name, edit, side_edit in (
        ("S-decoy", lambda t: t.assign(difference=str(a / "decoy.npy")), None),
        ("S-up", lambda t: t.assign(difference="../decoy.npy"), None),
        ("S-etc", lambda t: t.assign(images="/etc/*", background="/etc/*"), None),
        ("S-settings", None, lambda s: s.update(feature_settings=[1])),
        ("S-sidecar-list", None, "list"),
        ("S-slash", lambda t: t.assign(id=["a/b"] + list(t["id"][1:])), None),
        ("S-sensor", None, lambda s: s.update(sensor="x")),
    ):
        shutil.copytree(a / "S", a / name)
        if edit:
            edit(table.copy()).to_csv(a / name / "measured.csv", index=False)
        if side_edit == "list":
            (a / name / "measured.json").write_text("[]")
        elif side_edit:
            s = json.loads((a / "S" / "measured.json").read_text())
            side_edit(s)
            (a / name / "measured.json").write_text(json.dumps(s))


def run_case(script: str, args: list[str], limit: float) -> dict:
    work = Path(tempfile.mkdtemp(prefix="case-"))
    r, w = os.pipe()
    t0 = time.time()
    pid = os.fork()
    if pid == 0:  # child, in a process group of its own: a time limit stops what it started too
        os.close(r)
        os.setsid()
        os.chdir(work)
        try:
            code, out, err = invoke(script, args)
        except BaseException as exc:  # a traceback that escaped the command runner
            import traceback

            code, out, err = 1, "", "Traceback (escaped)\n" + "".join(traceback.format_exception(exc))
        os.write(w, json.dumps({"code": code, "out": out[-2000:], "err": err[-4000:]}).encode())
        os._exit(0)
    os.close(w)
    data = b""
    os.set_blocking(r, False)
    status = None
    while status is None:
        try:
            while chunk := os.read(r, 65536):
                data += chunk
        except BlockingIOError:
            pass
        done, st = os.waitpid(pid, os.WNOHANG)
        if done:
            status = st
        elif time.time() - t0 > limit:
            os.killpg(pid, signal.SIGKILL)
            _, status = os.waitpid(pid, 0)
            data = b""
        else:
            time.sleep(0.05)
    try:
        while chunk := os.read(r, 65536):
            data += chunk
    except BlockingIOError:
        pass
    os.close(r)
    try:  # whatever the case left running (a demo's sweep) goes with it
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    res = json.loads(data) if data else {"code": None, "out": "", "err": f"killed (status {status})"}
    res["seconds"] = time.time() - t0
    res["left"] = sorted(str(p.relative_to(work)) for p in work.rglob("*"))
    shutil.rmtree(work, ignore_errors=True)
    return res


def classify(kind: str, words: tuple[str, ...], res: dict) -> str:
    err = res["err"]
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("note:", "warning:"))]
    if res["code"] is None:
        return "time limit (work started)"
    if "Traceback" in err or "Traceback" in res["out"]:
        return "traceback"
    if kind == "edge":
        return "clean" if res["code"] in (0, 2) and (res["code"] == 0 or len(lines) == 1) else f"exit {res['code']}"
    if res["code"] == 0:
        return "accepted"
    if res["code"] != 2:
        return f"exit {res['code']}"
    if len(lines) != 1:
        return "several lines"
    if words and not any(w.lower() in lines[0].lower() for w in words):
        return "wrong name"
    if res["left"]:
        return "files left"
    return "clean"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default=None, help="run the cases whose command line holds this word")
    ap.add_argument("--json", default=None, help="write every case and its result here")
    ap.add_argument("--limit", type=float, default=90.0, help="seconds per case")
    ap.add_argument("--set", choices=("first", "fresh"), default="first", help="which set of cases")
    opts = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    assets = Path(tempfile.mkdtemp(prefix="badsweep-assets-"))
    build_assets(assets)
    if opts.set == "fresh":
        build_fresh_assets(assets)
    before = snapshot(assets)
    results = []
    chosen = cases() if opts.set == "first" else fresh_cases()
    todo = [x for x in chosen if opts.only is None or opts.only in " ".join([x[1], *x[2]])]
    for kind, script, args, words in todo:
        argv = [s.replace("{A}", str(assets)) for s in args]
        res = run_case(script, argv, opts.limit)
        verdict = classify(kind, words, res)
        results.append({"kind": kind, "cmd": " ".join([script, *args]), "verdict": verdict, **res})
        last = (res["err"].strip().splitlines() or [""])[-1][:150]
        print(f"{verdict:26s} {res['seconds']:6.1f}s  {script} {' '.join(args)[:90]}  | {last}", flush=True)
    changed = snapshot(assets) != before
    from collections import Counter

    n = len(results)
    counts = Counter(r["verdict"] for r in results)
    must = [r for r in results if r["kind"] == "refuse"]
    print(f"\n{n} cases ({len(must)} must be refused): " + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    print(f"clean {counts['clean']} of {n} ({100 * counts['clean'] / n:.1f} %); tracebacks {counts['traceback']}")
    print(f"refused cleanly: {sum(r['verdict'] == 'clean' for r in must)} of {len(must)}; assets changed: {changed}")
    if opts.json:
        Path(opts.json).write_text(json.dumps(results, indent=1))
    shutil.rmtree(assets, ignore_errors=True)


if __name__ == "__main__":
    main()

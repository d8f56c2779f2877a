"""The adopt loop on a SYNTHETIC lab, end to end with the ordinary commands
(docs/howto/your-own-sensor.md, "The loop on a SYNTHETIC lab").

A lab describes its sensor in ``lab.toml`` (default: the paper's).  Its true sensor differs by one
withheld sensor property (``--withheld NAME=VALUE``, an effect of ``elastimap gap effects`` applied
by the same switch a diagnosis adopts it with, :func:`elastimap.gap.adopt.adopt`); the study writes
it to ``true.toml`` and makes every piece of the lab's data with it, on ``--data-mesh`` (one level
finer than the model's ``--mesh``, so the lab is not elastimap's own model):

* ``data/measured``: the lab's phantoms (``gap synth --sensor true.toml --phantoms phantoms.csv``);
* ``data/phantom-frames``: their camera frames (``camera synth --sensor true.toml``), for the calibration;
* ``data/lesions``: held-out lesion frames over the sweep's design box (``camera synth --sensor true.toml``).

Round r (sensor S_0 = lab.toml, S_r = round r-1's ``adopted-sensor.toml``):
``sweep run --sensor S_r --phantoms`` -> ``train`` -> ``camera calibrate --sensor S_r --camera-csv``
(the lab's phantom frames) -> ``camera infer --sensor S_r --csv`` on the held-out lesions ->
(d, h, E) mean relative errors -> ``gap diagnose --sensor S_r`` -> the next S.  The loop stops when a
diagnosis adopts nothing or after ``--rounds``.  The no-effect case is the same lab whose true
sensor is the one it describes (data made with lab.toml): round 0's model, its own calibration and
lesions, its own diagnosis.

Every step is a subprocess of ``python -m elastimap.cli`` and is skipped when its output exists
(the sweep resumes itself), so an interrupted study resumes.  The table lands in ``OUT/loop.json``
and ``OUT/loop.md``.  Run::

    nice -n 10 python workflows/adopt_loop.py --out runs/adopt-loop --mesh coarse --data-mesh default --n 256
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import click
import numpy as np

from elastimap.cli_util import MeshLevel, mesh_option

#: the withheld effect of the study in the docs, chosen before any result: the tissue-side probe
#: layer is 200 kPa where the lab (the paper) says 300 kPa, a PDMS batch softer by a third.
WITHHELD = "probe_E1=200"


def elastimap(*args: str, log: Path) -> None:
    """One ordinary command (``python -m elastimap.cli ARGS``); its output goes to ``log``; a failure ends the study."""
    cmd = [sys.executable, "-m", "elastimap.cli", *map(str, args)]
    log.parent.mkdir(parents=True, exist_ok=True)
    click.echo("$ elastimap " + " ".join(map(str, args)), err=True)
    with open(log, "a") as fh:
        fh.write("$ elastimap " + " ".join(map(str, args)) + "\n")
        fh.flush()
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise click.ClickException(
            f"elastimap {args[0]} {args[1] if len(args) > 1 else ''} failed (exit {rc}); see {log}"
        )


def sensors(lab: str | None, withheld: str):
    """The lab's description (``lab``, default the paper's) and its true sensor: it with the withheld
    effect (``NAME=VALUE``, :func:`elastimap.gap.adopt.adopt`; the same description for ``none``)."""
    from elastimap.gap import effects as fx
    from elastimap.gap.adopt import adopt
    from elastimap.sensor import Sensor, load

    sensor = load(lab, "lab") if lab else Sensor().replace(name="lab")
    found = {}
    if withheld != "none":
        for e, m in fx.parse_spec(withheld, table=fx.for_sensor(sensor)):
            found[e.name] = [float(m)]
    return sensor, (adopt(sensor, found, name="lab-true").sensor if found else sensor)


def write_sensors(out: Path, lab: str | None, withheld: str) -> tuple[Path, Path]:
    """``lab.toml`` (the lab's description) and ``true.toml`` (:func:`sensors`) in ``out``, kept when there."""
    from elastimap.sensor import dumps

    sensor, truth = sensors(lab, withheld)
    lab_p, true_p = out / "lab.toml", out / "true.toml"
    if not lab_p.exists():
        lab_p.write_text(dumps(sensor, "the lab's description of its sensor"))
    if not true_p.exists():
        true_p.write_text(dumps(truth, f"SYNTHETIC: the lab's true sensor (withheld: {withheld})"))
    return lab_p, true_p


def write_designs(out: Path, n_phantoms: int, n_lesions: int, seed: int) -> None:
    """``phantoms.csv`` (the lab's phantoms, the diagnosis's LHS) and ``lesions-truth.csv`` (held-out
    lesions: an LHS over the sweep's default design box, another seed than the sweep's)."""
    import pandas as pd

    from elastimap.gap.synth import phantom_design
    from elastimap.sweep.design import design_points, parse_ranges

    p = out / "phantoms.csv"
    if not p.exists():
        dhe = phantom_design(n_phantoms, seed)
        pd.DataFrame(
            {"name": [f"ph{i:02d}" for i in range(len(dhe))], "d": dhe[:, 0], "h": dhe[:, 1], "E": dhe[:, 2]}
        ).to_csv(p, index=False)
    q = out / "lesions-truth.csv"
    if not q.exists():
        pts = design_points(n_lesions, "lhs", 1000 + seed, parse_ranges(None))
        pd.DataFrame(
            {"id": [f"les{i:02d}" for i in range(len(pts))], **{k: [round(x[k], 3) for x in pts] for k in "dhE"}}
        ).to_csv(q, index=False)


def frames(sensor: Path, table: Path, folder: Path, col: str, mesh: str, n_frames: int, seed: int, log: Path) -> Path:
    """Camera frames of every row of ``table`` (``camera synth --sensor``) and the CSV that lists them
    (``name|id,images,background``, relative to ``folder``)."""
    import pandas as pd

    csv = folder / "frames.csv"
    if csv.exists():
        return csv
    rows = []
    for k, r in pd.read_csv(table).iterrows():
        name = str(r[col])
        if not (folder / f"synthetic_{name}.json").exists():
            elastimap(
                "camera", "synth", "--sensor", sensor, "--d", r["d"], "--h", r["h"], "--E", r["E"], "--mesh", mesh,
                "--frames", n_frames, "--seed", seed + k, "--name", name, "--out", folder, log=log,
            )  # fmt: skip
        rows.append(
            {
                col: name,
                "images": f"synthetic_{name}_f[0-9]*.png",
                "background": f"synthetic_{name}_background_f[0-9]*.png",
            }
        )
    pd.DataFrame(rows).to_csv(csv, index=False)
    return csv


def make_data(out: Path, sensor: Path, tag: str, a: dict, log: Path) -> dict:
    """The lab's SYNTHETIC data made with ``sensor``: measured phantoms, phantom frames, lesion frames."""
    d = out / f"data{tag}"
    meas = d / "measured"
    if not (meas / "measured.csv").exists():
        elastimap(
            "gap", "synth", "--sensor", sensor, "--phantoms", out / "phantoms.csv", "--mesh", a["data_mesh"],
            "--frames", a["frames"], "--seed", a["seed"], "--jobs", a["jobs"], "--cache", out / "cache",
            "--no-progress", "--overwrite", "--out", meas, log=log,
        )  # fmt: skip
    pf = frames(
        sensor,
        out / "phantoms.csv",
        d / "phantom-frames",
        "name",
        a["data_mesh"],
        a["frames"],
        100 * a["seed"] + 1,
        log,
    )
    lf = frames(
        sensor, out / "lesions-truth.csv", d / "lesions", "id", a["data_mesh"], a["frames"], 100 * a["seed"] + 51, log
    )
    return {"measured": meas, "phantom_frames": pf, "lesions": lf}


def mre(infer_json: Path, truth_csv: Path) -> dict:
    """Mean relative error (%) of the held-out lesions' point estimates, per quantity, and how many
    estimates ``infer`` flagged (out of range or not identifiable)."""
    import pandas as pd

    rows = {str(r["id"]): r for r in json.loads(infer_json.read_text())}
    truth = pd.read_csv(truth_csv)
    out = {"n": len(truth), "flagged": int(sum(not rows[str(i)]["ok"] for i in truth["id"]))}
    for q in "dhE":
        est = np.array([float(rows[str(i)][q]) for i in truth["id"]])
        rel = np.abs(est - truth[q].to_numpy()) / truth[q].to_numpy()
        out[f"{q}_mre"] = float(100 * np.nanmean(rel))
        out[f"{q}_n"] = int(np.isfinite(rel).sum())
    return out


def diagnosis_row(folder: Path) -> dict:
    """What a diagnosis found (``diagnosis.json``): baseline χ², its threshold, outcome, winner, adoption."""
    res = json.loads((folder / "diagnosis.json").read_text())
    ev = res["evaluation"]
    row = {
        "chi2_baseline": ev["chi2_baseline"],
        "chi2_threshold": ev["chi2_threshold"],
        "n_terms": ev["n_terms"],
        "outcome": ev["outcome"],
        "winner": ev.get("winner"),
        "ranking": [
            {"effect": r["effect"], "magnitude": r.get("magnitude"), "held_out_chi2": r["ssr_cv"]}
            for r in ev.get("ranking", [])[:3]
        ],
        "adoption": res["adoption"]["note"],
        "adopted": [r for r in res["adoption"]["rows"] if r["adopted"]],
    }
    if row["winner"]:  # its held-out χ²: the ranking's row of the winner, or of the family that fitted it
        src = ev["reported"][row["winner"]].get("via") or row["winner"]
        rk = next((x for x in ev.get("ranking", []) if x["effect"] == src), None)
        row["winner_held_out_chi2"] = None if rk is None else rk["ssr_cv"]
    return row


def run_round(out: Path, r: int, sensor: Path, data: dict, a: dict, log: Path, model: Path | None = None) -> dict:
    """One round on ``sensor``: sweep -> train -> calibrate -> infer -> errors -> diagnose."""
    rd = out / f"round{r}" if isinstance(r, int) else out / str(r)
    rd.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    timing = {}
    if model is None:
        sweep, run = rd / "sweep", rd / "model"
        model = run / "model-scg"  # the saved ensemble of ``train --algo scg``
        elastimap(
            "sweep", "run", "--sensor", sensor, "--n", a["n"], "--mesh", a["mesh"], "--phantoms", "--jobs", a["jobs"],
            "--seed", a["seed"], "--no-progress", "--out", sweep, log=log,
        )  # fmt: skip
        timing["sweep_s"] = time.time() - t0
        if not (model / "model.json").exists():
            elastimap(
                "train", "--data", sweep, "--algo", "scg", "--validate", "hov", "--repeats", a["repeats"],
                "--hidden", a["hidden"], "--seed", a["seed"], "--no-progress", "--overwrite", "--out", run, log=log,
            )  # fmt: skip
        timing["train_s"] = time.time() - t0 - timing["sweep_s"]
    t1 = time.time()
    cal = rd / "calibration.json"
    if not cal.exists():
        elastimap(
            "camera", "calibrate", "--sensor", sensor, "--phantoms", out / "phantoms.csv", "--camera-csv",
            data["phantom_frames"], "--mesh", a["mesh"], "--out", cal, log=log,
        )  # fmt: skip
    est = rd / "infer.json"
    if not est.exists():
        elastimap(
            "camera", "infer", "--sensor", sensor, "--model", model, "--calibration", cal, "--csv", data["lesions"],
            "--out", est, log=log,
        )  # fmt: skip
    timing["calibrate_infer_s"] = time.time() - t1
    t2 = time.time()
    diag = rd / "diagnosis"
    if not (diag / "diagnosis.json").exists():
        extra = ["--effects", a["effects"]] if a["effects"] else []
        extra += ["--error-mesh", a["error_mesh"]] if a["error_mesh"] else []
        elastimap(
            "gap", "diagnose", "--sensor", sensor, "--measured", data["measured"], "--mesh", a["mesh"], "--no-inverse",
            "--jobs", a["jobs"], "--cache", out / "cache", "--no-progress", *extra, "--out", diag, log=log,
        )  # fmt: skip
    timing["diagnose_s"] = time.time() - t2
    timing["wall_s"] = time.time() - t0
    tf = rd / "timing.json"  # a resumed round keeps the times of the run that did its work
    if tf.exists():
        timing = json.loads(tf.read_text())
    else:
        timing = {k: round(v, 1) for k, v in timing.items()}
        tf.write_text(json.dumps(timing))
    from elastimap.sensor import load

    s = load(sensor)
    return {
        "round": r,
        "sensor": str(sensor.relative_to(out)),
        "sensor_name": s.name,
        "sensor_hash": s.hash(),
        "model": str(model.relative_to(out)),
        **mre(est, out / "lesions-truth.csv"),
        **diagnosis_row(diag),
        **timing,
    }


def ci(row: dict) -> str:
    """`` [lo, hi]`` of an adopted row's 95 % interval, or nothing."""
    c = row.get("magnitude_ci")
    return f" [{c[0]:.4g}, {c[1]:.4g}]" if c else ""


def table_md(doc: dict) -> str:
    """The loop's table as Markdown."""
    lines = [
        "| round | sensor (hash) | d / h / E MRE on held-out lesions (%) | flagged | baseline χ² (threshold) over N | "
        "outcome | adopted | wall |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in doc["rounds"]:
        ad = "; ".join(f"{x['effect']} = {x['magnitude']:.4g} {x['unit']}{ci(x)}" for x in r["adopted"]) or "nothing"
        win = r["outcome"] + (
            f" by {r['winner']} (held-out χ² {r['winner_held_out_chi2']:.3g})" if r.get("winner_held_out_chi2") else ""
        )
        lines.append(
            f"| {r['round']} | `{r['sensor_name']}` (`{r['sensor_hash']}`) | {r['d_mre']:.1f} / {r['h_mre']:.1f} / "
            f"{r['E_mre']:.1f} | {r['flagged']}/{r['n']} | {r['chi2_baseline']:.4g} ({r['chi2_threshold']:.4g}) over "
            f"{r['n_terms']} | {win} | {ad} | {r['wall_s'] / 60:.1f} min |"
        )
    return "\n".join(lines) + "\n"


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Study folder (resumed when it exists).")
@click.option(
    "--lab", default=None, type=click.Path(dir_okay=False), help="The lab's description [default: the paper's sensor]."
)
@click.option(
    "--withheld",
    default=WITHHELD,
    show_default=True,
    help="NAME=VALUE of the true sensor's withheld effect ('none': no effect).",
)
@mesh_option(default="coarse", help="Mesh level of the lab's model (sweep, calibrate, diagnose).")
@click.option(
    "--data-mesh",
    type=MeshLevel(),
    default="default",
    show_default=True,
    help="Mesh level of the lab's SYNTHETIC data.",
)
@click.option("--n", "n", type=int, default=256, show_default=True, help="Design samples per round's sweep.")
@click.option("--phantoms", "n_phantoms", type=int, default=12, show_default=True, help="The lab's phantoms.")
@click.option("--lesions", "n_lesions", type=int, default=12, show_default=True, help="Held-out lesions.")
@click.option("--frames", type=int, default=10, show_default=True, help="Camera frames per press.")
@click.option(
    "--rounds", type=int, default=3, show_default=True, help="Most rounds (the loop stops when nothing is adopted)."
)
@click.option("--repeats", type=int, default=5, show_default=True, help="train --repeats.")
@click.option("--hidden", default="25,10", show_default=True, help="train --hidden.")
@click.option("--effects", default=None, help="gap diagnose --effects [default: the diagnosis's own list].")
@click.option("--error-mesh", default=None, help="gap diagnose --error-mesh [default: the next finer level].")
@click.option(
    "--no-effect-case/--no-no-effect-case", default=True, show_default=True, help="Also run the no-effect case."
)
@click.option(
    "--seed", type=int, default=0, show_default=True, help="Seeds the designs, the sweeps, training and frame noise."
)
@click.option("--jobs", type=int, default=2, show_default=True, help="Worker processes of the solves.")
def main(
    out,
    lab,
    withheld,
    mesh,
    data_mesh,
    n,
    n_phantoms,
    n_lesions,
    frames,
    rounds,
    repeats,
    hidden,
    effects,
    error_mesh,
    no_effect_case,
    seed,
    jobs,
):
    """The adopt loop on a SYNTHETIC lab (sweep -> train -> calibrate -> infer -> diagnose -> adopt, repeated)."""
    a = dict(
        mesh=mesh, data_mesh=data_mesh, n=n, frames=frames, repeats=repeats, hidden=hidden, effects=effects,
        error_mesh=error_mesh, seed=seed, jobs=jobs,
    )  # fmt: skip
    from elastimap.errors import UserError

    for flag, v, lo in (
        ("--n", n, 1), ("--phantoms", n_phantoms, 4), ("--lesions", n_lesions, 1), ("--frames", frames, 2),
        ("--rounds", rounds, 1), ("--repeats", repeats, 1), ("--jobs", jobs, 1),
    ):  # fmt: skip
        if v < lo:
            raise UserError(flag, f"must be an integer >= {lo} (got {v})")
    try:
        sensors(lab, withheld)  # the descriptions are checked before anything is written
    except UserError as exc:
        raise UserError("--lab" if exc.param == "lab" else "--withheld", exc.message) from None
    o = Path(out)
    o.mkdir(parents=True, exist_ok=True)
    log = o / "commands.log"
    t0 = time.time()
    lab_p, true_p = write_sensors(o, lab, withheld)
    write_designs(o, n_phantoms, n_lesions, seed)
    data = make_data(o, true_p, "", a, log)
    tf = o / "data-timing.json"  # kept from the run that made the data
    if not tf.exists():
        started = datetime.fromtimestamp(t0, UTC).strftime("%Y-%m-%d %H:%M UTC")
        tf.write_text(json.dumps({"data_s": round(time.time() - t0, 1), "started": started}))
    first = json.loads(tf.read_text())
    doc = {
        "synthetic": True,
        "command": "python workflows/adopt_loop.py " + " ".join(sys.argv[1:]),
        "date": first.get("started"),  # when the study started (a resumed run keeps it)
        "rendered": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.node()} ({os.cpu_count()} cores)",
        "withheld": withheld,
        "settings": a,
        "data_s": first["data_s"],
        "rounds": [],
    }
    sensor, rows, none = lab_p, [], None
    for r in range(rounds):
        row = run_round(o, r, sensor, data, a, log)
        rows.append(row)
        if r == 0 and no_effect_case and withheld != "none":  # round 0's model, on the lab without the effect
            data0 = make_data(o, lab_p, "-none", a, log)
            none = run_round(o, "no-effect", lab_p, data0, a, log, model=o / "round0" / "model" / "model-scg")
        adopted = o / f"round{r}" / "diagnosis" / "adopted-sensor.toml"
        if not row["adopted"] or not adopted.exists():
            break
        sensor = adopted
    doc["rounds"] = rows + ([none] if none else [])
    doc["wall_s"] = round(time.time() - t0, 1)
    (o / "loop.json").write_text(json.dumps(doc, indent=2))
    md = table_md(doc)
    (o / "loop.md").write_text(
        f"SYNTHETIC lab (withheld: {withheld}); `{doc['command']}`, {doc['date']}, {doc['machine']}\n\n" + md
    )
    click.echo(md)


if __name__ == "__main__":
    from elastimap.cli_util import run

    sys.exit(run(main, prog_name="workflows/adopt_loop.py"))

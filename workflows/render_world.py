"""Camera frames of a world elastimap did not make: a folder of presses in the format of
``shared/devdata/independent-fem`` (``sets.csv``, ``raw_*.npy`` / ``ref_*.npy``: the probe bottom's
compression w = u_z + δ in mm, 0.5 mm pixels) rendered through elastimap's nominal camera
(:class:`elastimap.camera.optics.SensorModel`) into what a lab would hand the product::

    python -m elastimap.workflows.render_world --world /work/shared/devdata/independent-fem \\
        --sets none,tissueE65 --frames 10 --out /tmp/devframes

Per set ``<out>/<set>/`` holds 16-bit PNG frames (a lesion and a background press per phantom,
independent noise) and four tables, every path relative to the folder:

* ``measured.csv`` -- ``id,d,h,E,images,background`` of all phantoms: a measured set for
  ``elastimap gap diagnose`` (docs/gap.md, 'Measured-data format'), no sidecar;
* ``phantoms.csv`` + ``camera.csv`` -- the first nine phantoms (the set's calibration phantoms) as
  ``camera calibrate --phantoms phantoms.csv --camera-csv camera.csv`` reads them;
* ``lesions.csv`` -- ``id,images,background`` of all phantoms for ``camera infer --csv``; the truth
  stays in ``measured.csv``.

The frames are simulated (another FEM through elastimap's camera model), so their metadata says
``synthetic``; the presses are not elastimap's, which is the point (the open-world rule,
DEVELOPERS.md).  A study tool: nothing in the product imports it.
"""

from __future__ import annotations

import csv
import os
import tempfile
from pathlib import Path

import click
import numpy as np

#: the presses' pixel (mm), from the world folder's README
PIXEL = 0.5
#: how many of a set's phantoms are its calibration phantoms (the README: "the first nine")
N_CALIBRATION = 9


def read_sets(world: str | os.PathLike) -> dict[str, list[dict]]:
    """``sets.csv`` of ``world`` grouped by set, in file order."""
    out: dict[str, list[dict]] = {}
    with open(Path(world) / "sets.csv", newline="") as f:
        for r in csv.DictReader(f):
            out.setdefault(r["set"], []).append(r)
    return out


def _write_csv(path: Path, header: list[str], rows: list[list]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def render_set(world: Path, rows: list[dict], out: Path, frames: int, seed: int, lens_k1: float = 0.0) -> None:
    """Render one set's phantoms into ``out`` (a new folder) with the four tables; ``lens_k1``: the
    camera's radial lens distortion (``SensorModel.lens_k1``; 0, the nominal camera)."""
    from elastimap.camera.frames import write_frames
    from elastimap.camera.optics import SensorModel, render_pair

    model = SensorModel(lens_k1=lens_k1).validate()
    rng = np.random.default_rng(seed)
    (out / "frames").mkdir(parents=True)
    table = []
    for r in rows:
        raw, ref = (np.load(world / r[k]) for k in ("raw", "ref"))
        lesion, bg = render_pair(model, raw, raw - ref, PIXEL, frames, rng)
        pid = r["phantom"]
        meta = {"world": str(world), "set": r["set"], "phantom": pid, "frames": frames, "seed": seed}
        write_frames(lesion, out / "frames", f"{pid}_lesion", metadata=meta)
        write_frames(bg, out / "frames", f"{pid}_background", metadata=meta)
        imgs, bgs = f"frames/synthetic_{pid}_lesion_f*.png", f"frames/synthetic_{pid}_background_f*.png"
        table.append([pid, r["d_mm"], r["h_mm"], r["E_kPa"], imgs, bgs])
    _write_csv(out / "measured.csv", ["id", "d", "h", "E", "images", "background"], table)
    _write_csv(out / "lesions.csv", ["id", "images", "background"], [[t[0], t[4], t[5]] for t in table])
    cal = table[:N_CALIBRATION]
    _write_csv(out / "phantoms.csv", ["name", "d", "h", "E"], [t[:4] for t in cal])
    _write_csv(out / "camera.csv", ["name", "images", "background"], [[t[0], t[4], t[5]] for t in cal])


@click.command()
@click.option("--world", required=True, type=click.Path(exists=True, file_okay=False), help="Folder with sets.csv.")
@click.option("--sets", default=None, help="Comma-separated set names (default: all in sets.csv).")
@click.option("--frames", default=10, show_default=True, type=click.IntRange(1, 200), help="Frames per press.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1), help="Noise seed.")
@click.option(
    "--lens-k1",
    default=0.0,
    show_default=True,
    type=click.FloatRange(-0.2, 0.5),
    help="The camera's radial lens distortion k1 (fractional shift of the footprint corner; 0: the nominal "
    "camera; docs/camera.md, 'Synthetic TIR sensor model (`elastimap.camera.optics.SensorModel`)').",
)
@click.option("--out", required=True, type=click.Path(file_okay=False), help="New folder for the rendered sets.")
def cli(world, sets, frames, seed, lens_k1, out):
    """Render a world's presses through elastimap's nominal camera as lab-style measured sets."""
    world, out = Path(world), Path(out)
    if out.exists():
        raise click.UsageError(f"--out: {out} exists; name a new folder")
    groups = read_sets(world)
    names = sets.split(",") if sets else list(groups)
    unknown = [n for n in names if n not in groups]
    if unknown:
        raise click.BadParameter(f"no set {unknown[0]!r} in sets.csv (have {', '.join(groups)})", param_hint="--sets")
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    for i, n in enumerate(names):
        render_set(world, groups[n], stage / n, frames, seed + i, lens_k1)
        click.echo(f"{n}: {len(groups[n])} phantoms, {frames} frames each")
    os.chmod(stage, 0o777 & ~_umask())
    stage.rename(out)
    click.echo(f"wrote {out}")


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def main(argv=None):
    return cli.main(args=argv, prog_name="render_world")


if __name__ == "__main__":
    main()

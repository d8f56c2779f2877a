"""The ``camera`` set of the identifiability map: Cramér–Rao bounds from camera frames (SYNTHETIC camera).

    elastimap study cameramap compute --shard 0/2 --out runs/cameramap   # and 1/2 beside it
    elastimap study cameramap install --out runs/cameramap

The map's other sets assume white image noise of 1 % of each image's peak.  A camera's noise is
not relative to the peak: per pixel it is the shot and read noise of the frames, turned into
deflection through the optics' slope at the background press (``deflection_noise_map``), the same
for a large and a small lesion.  So a large shallow lesion is measured far better than 1 % and a
small deep one far worse.  This study gives the bound for what a camera actually measures:

* at every point θ = (d, h, E) of the map's grid (:func:`elastimap.identify.bounds.grid`), the
  difference image's exact derivative J = ∂I/∂(d, h, ln E) on the morphed forward map at
  ``--mesh`` (:meth:`elastimap.identify.forward_maps.ForwardMap.tangent`, one solve and three
  back-solves; no surrogate, no finite differences);
* σ_p (mm) of every image pixel p: the nominal SYNTHETIC camera
  (:class:`elastimap.camera.optics.SensorModel`) with ``--frames`` lesion and as many background
  frames, linearised at that point's background press
  (:func:`elastimap.camera.optics.deflection_noise_map`);
* Fisher information F = Jᵀ diag(σ⁻²) J, Cramér–Rao relative std r = (√C_dd / d, √C_hh / h,
  √C_lnE,lnE), C = F⁻¹ (:func:`camera_bound`, with :func:`elastimap.identify.bounds.crb_relstd`).

``install`` adds the set ``camera`` (and the nominal noise map ``camera_sigma``, mm per pixel, and
``camera_frames``) to the shipped map (:data:`elastimap.identify.idmap.DEFAULT_MAP`) through
:func:`elastimap.workflows.studies.crbmap.install_map`, keeping every other entry of the file
(its sets and crbmap's raw surrogate bounds and FD scales).  Inference from
frames scales the set by the frames' own noise against ``camera_sigma``
(:meth:`elastimap.identify.idmap.IdentifiabilityMap.camera_scale`).  ``crbmap --install`` writes
a map without this set: run ``install`` again after it.  The bound holds for the model's physics
alone: the forward model's own error is not in it (docs/identifiability.md, 'What camera frames identify', measures how far
that error reaches).
"""

from __future__ import annotations

import glob
import os
import tempfile
import time

import click
import numpy as np

from elastimap.cli_util import mesh_option, run, shard_option
from elastimap.errors import UserError


def camera_bound(J: np.ndarray, sigma: np.ndarray, theta) -> np.ndarray:
    """Cramér–Rao relative std (d, h, E) at ``theta`` (d mm, h mm, E kPa) from the image's derivative
    ``J`` (3, ny, nx) = ∂I/∂(d mm, h mm, E kPa) (mm per unit) and the per-pixel noise ``sigma`` (mm,
    image-shaped): F = Jᵀ diag(σ⁻²) J in (d, h, ln E)."""
    from elastimap.identify.bounds import crb_relstd

    theta = np.asarray(theta, float)
    Jp = np.asarray(J, float).reshape(3, -1).T * np.array([1.0, 1.0, theta[2]])  # ∂I/∂ln E = E ∂I/∂E
    Jw = Jp / np.asarray(sigma, float).reshape(-1, 1)  # whitened: rows / σ_p
    return crb_relstd((Jw.T @ Jw)[None], theta[None])[0]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """The camera-frames set of the identifiability map (see the module docstring)."""


@main.command("compute")
@mesh_option("coarse", "Mesh level of the morphed forward map.")
@click.option("--frames", default=30, show_default=True, type=int, help="Lesion (and background) frames.")
@shard_option("K/N: this process takes the (d, depth) columns i % N == K.")
@click.option("--out", required=True, help="Folder for the shard files (resumable).")
def compute_cmd(mesh, frames, shard, out):
    """Bounds at the grid points of this shard (one file per (d, depth) column, resumable)."""
    from tqdm import tqdm

    from elastimap.camera.optics import background_deflection, deflection_noise_map
    from elastimap.identify.bounds import grid
    from elastimap.identify.forward_maps import forward_map

    if frames < 1:
        raise UserError("--frames", f"must be >= 1 (got {frames})")
    k, n = shard
    os.makedirs(out, exist_ok=True)
    T, (ds, us, Es) = grid()
    cols = T.reshape(len(ds) * len(us), len(Es), 3)
    fwd = forward_map(mesh, "morph")
    for c in tqdm(range(k, cols.shape[0], n), desc=f"camera bound ({mesh} morphed map, shard {k}/{n})"):
        path = os.path.join(out, f"col-{c:03d}.npz")
        if os.path.exists(path):
            continue
        t0 = time.process_time()
        r, sig = np.empty((len(Es), 3)), None
        for j, (d, h, E) in enumerate(cols[c]):
            res, J = fwd.pin(d, h).tangent(d, h, E)
            img, raw = np.asarray(res.image, float), np.asarray(res.image_raw, float)
            sig = deflection_noise_map(background_deflection(raw, img), float(res.pixel), frames)
            r[j] = camera_bound(J, sig, (d, h, E))
        tmp = os.path.join(out, f".col-{c:03d}.tmp.npz")
        np.savez(tmp, col=c, r=r, theta=cols[c], sigma=sig, mesh=mesh, frames=frames, cpu=time.process_time() - t0)
        os.replace(tmp, path)


@main.command("install")
@click.option("--out", required=True, help="The folder 'compute' wrote.")
@click.option("--map", "map_path", default=None, help="Map file to add the set to (default: the shipped map).")
def install_cmd(out, map_path):
    """Add the ``camera`` set to the map (every column must be there)."""
    from elastimap.identify.bounds import grid
    from elastimap.identify.idmap import DEFAULT_MAP, IdentifiabilityMap

    from .crbmap import install_map

    T, (ds, us, Es) = grid()
    ncol = len(ds) * len(us)
    files = sorted(glob.glob(os.path.join(out, "col-*.npz")))
    got = {int(np.load(f)["col"]): f for f in files}
    missing = [c for c in range(ncol) if c not in got]
    if missing:
        raise UserError("--out", f"{out}: {len(missing)} of {ncol} grid columns missing (run 'compute' first)")
    zs = [np.load(got[c]) for c in range(ncol)]
    meshes, frames = {str(z["mesh"]) for z in zs}, {int(z["frames"]) for z in zs}
    if len(meshes) != 1 or len(frames) != 1:
        raise UserError("--out", f"{out}: columns of different --mesh / --frames ({meshes}, {frames})")
    theta = np.concatenate([z["theta"] for z in zs])
    if not np.allclose(theta, T):
        raise UserError("--out", f"{out}: the columns are not on this map's grid")
    r = np.concatenate([z["r"] for z in zs])
    (mesh,), (nframes,) = meshes, frames
    sigma = np.median(np.stack([z["sigma"] for z in zs]), axis=0)
    dest = map_path or DEFAULT_MAP
    m = IdentifiabilityMap.load(dest)
    if not (np.allclose(m.d, ds) and np.allclose(m.u, us) and np.allclose(m.E, Es)):
        raise UserError("--map", f"{dest}: not on the grid of elastimap.identify.bounds.grid")
    # every entry of the file stays (crbmap's raw surrogate bounds and FD scales, which
    # ``crbmap --surrogate-from`` reads, are not part of IdentifiabilityMap); the camera ones are added
    with np.load(dest, allow_pickle=False) as z:
        entries = {k: z[k] for k in z.files}
    entries.update(
        camera=r,
        camera_sigma=sigma,
        camera_frames=nframes,
        source=m.source.split("; camera set:")[0]
        + f"; camera set: python -m elastimap.workflows.studies.cameramap on the {mesh} morphed map, "
        f"nominal SYNTHETIC camera, {nframes} frames",
    )
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "map.npz")
        np.savez(src, **entries)
        install_map(src, dest)
    click.echo(f"camera set ({ncol} columns, {T.shape[0]} points) added to {dest}")


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="elastimap study cameramap")

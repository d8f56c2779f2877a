"""The benchmark's lesions (SYNTHETIC): the held-out design over the whole design box or a region of
it (:func:`draw_lesions`), the "world" that images them (:func:`truth_solve`, the remeshing solver),
the camera session (:func:`session_sensor`), where the shipped map calls each quantity identifiable
(:func:`identifiable_at`) and the ``lesions`` stage that solves them into ``OUT/solves``."""

from __future__ import annotations

import os
import time

import click
import numpy as np

from elastimap.cli_util import shard_option, sizing_option

TRUTH_SEED = 2026


#: how many design points per wanted lesion ``draw_lesions(inside=...)`` draws (the region of
#: E from frames is about 3 % of the design)
INSIDE_OVERDRAW = 200


def draw_lesions(n: int, seed: int = TRUTH_SEED, inside: str | None = None, outside: str | None = None) -> np.ndarray:
    """(n, 3) lesions (d mm, h mm, E kPa): Latin hypercube over d, the admissible depth fraction and ln E.

    ``inside`` (d, h or E): a region-stratified set instead -- the first n of a Latin hypercube of
    ``INSIDE_OVERDRAW`` n points at which the shipped map's ``frames`` set calls that quantity
    identifiable (10 %), decided from the truth before any fit, so that a quantity identifiable
    over a small part of the design can be scored on enough lesions.  ``outside``: the same, at
    points where the map does NOT call it identifiable (to score the intervals there on more than
    the quarter of a design draw that lies outside d's region).  At most one of the two."""
    from elastimap.errors import UserError

    if inside is not None and outside is not None:
        raise UserError("outside", f"give inside or outside, not both (got inside={inside!r}, outside={outside!r})")
    if inside is None and outside is None:
        return _lhs_lesions(n, seed)
    q = inside or outside
    cand = _lhs_lesions(INSIDE_OVERDRAW * n, seed)
    ident = identifiable_at(cand, "frames")[:, "dhE".index(q)]
    keep = cand[ident if inside is not None else ~ident]
    if len(keep) < n:
        where = "identifiable" if inside is not None else "not identifiable"
        raise UserError("n", f"at most {len(keep)} lesions with {q} {where} at seed {seed} (got {n})")
    return keep[:n]


def lesion_design(n: int, seed: int, inside: str | None, outside: str | None = None) -> np.ndarray:
    """:func:`draw_lesions` for the commands: its errors name the flags."""
    from elastimap.errors import UserError

    try:
        return draw_lesions(n, seed, inside, outside)
    except UserError as exc:
        raise UserError("--n" if exc.param == "n" else "--outside", exc.message) from None


def design_record(n: int, seed: int, inside: str | None, outside: str | None) -> dict:
    """The ``design`` a lesion record keeps (``outside`` only when given, so whole-design and
    ``--inside`` records read as before)."""
    rec = {"n": n, "seed": seed, "inside": inside}
    if outside is not None:
        rec["outside"] = outside
    return rec


def drawn_note(design: dict | None) -> str:
    """Where a record's lesions were drawn, for the report's header and the figure's title ("" for
    the whole design box)."""
    design = design or {}
    if design.get("inside"):
        return f"drawn where the map's 'frames' set calls {design['inside']} identifiable"
    if design.get("outside"):
        return f"drawn where the map's 'frames' set does not call {design['outside']} identifiable"
    return ""


def _lhs_lesions(n: int, seed: int) -> np.ndarray:
    from scipy.stats import qmc

    from elastimap.dataset.schema import DESIGN_BOX
    from elastimap.solver.params import depth_range

    (d0, d1), (e0, e1) = DESIGN_BOX["d"], DESIGN_BOX["E"]
    u = qmc.LatinHypercube(d=3, seed=seed).random(n)
    d = d0 + (d1 - d0) * u[:, 0]
    lo, hi = np.array([depth_range(x) for x in d]).T
    h = lo + u[:, 1] * (hi - lo)
    E = np.exp(np.log(e0) + (np.log(e1) - np.log(e0)) * u[:, 2])
    return np.column_stack([d, h, E])


SESSIONS = ("nominal", "drift")


def session_sensor(sensor, rng: np.random.Generator):
    """The camera of one SYNTHETIC session: ``sensor`` with each LED's power times U(0.8, 1.2) and
    the vignetting drawn from U(0.05, 0.3) -- what drifts between a calibration and a clinic's
    session; inference keeps the calibration's nominal model (the background frames' flat field
    should absorb both)."""
    return sensor.replace(
        led_power=tuple(float(p) * float(rng.uniform(0.8, 1.2)) for p in sensor.led_power),
        vignetting=float(rng.uniform(0.05, 0.3)),
    )


def truth_solve(d, h, E, mesh: str, cache: str, sizing: str = "fixed") -> dict:
    from elastimap.workflows.solves import cached_solve

    return cached_solve(float(d), float(h), float(E), mesh=mesh, cache=cache, sizing=sizing)


def world_label(mesh: str, sizing: str) -> str:
    return f"remeshing solver, {mesh} mesh" + (", by_d sizing" if sizing == "by_d" else "")


TRUTH_SIZING = sizing_option(
    flag="--truth-sizing",
    help="Element sizing of the world's mesh near the inclusion (by_d: sized by the inclusion's diameter).",
)


def _region_option(flag: str, where: str, why: str):
    """``--inside`` / ``--outside``: a region-stratified lesion set (:func:`draw_lesions`)."""
    return click.option(
        flag,
        type=click.Choice(tuple("dhE")),
        default=None,
        help=f"A region-stratified lesion set: only design points where the shipped map's frames set {where} "
        f"this quantity identifiable ({why}). Give the same value to lesions and run.",
    )


INSIDE = _region_option("--inside", "calls", "draw_lesions; for scoring E, identifiable over ~3 % of the design")
OUTSIDE = _region_option(
    "--outside", "does NOT call", "to score intervals outside a region on enough lesions; not with --inside"
)


REGION_SETS = ("frames", "camera", "image")


def identifiable_at(truth: np.ndarray, mset: str = "frames") -> np.ndarray:
    """(n, 3) bool: the shipped identifiability map (set ``mset``, 10 %) calls d, h, E identifiable at
    the truth.  ``frames``: what inference from frames uses (the larger of the camera and image
    bounds); ``camera``: the nominal camera at the map's frame count (the benchmark's camera);
    ``image``: 1 % of the peak per pixel (the regions of the tables before 2026-11-25)."""
    from elastimap.identify.idmap import IdentifiabilityMap

    r, _ = IdentifiabilityMap.load().bound(truth, mset)
    return r <= 0.10


@click.command("lesions")
@click.option("--n", "n", default=120, show_default=True, type=int, help="Held-out lesions.")
@click.option("--seed", default=TRUTH_SEED, show_default=True, type=int, help="Seed of the lesion design.")
@click.option("--truth-mesh", default="default", show_default=True, help="Mesh level of the world's remeshing solver.")
@TRUTH_SIZING
@INSIDE
@OUTSIDE
@shard_option("K/N: this process solves items i with i % N == K.")
@click.option(
    "--first", default=0, show_default=True, type=int, help="Only the first K lesions of the design (0: all)."
)
@click.option("--out", required=True, help="Benchmark folder (solves land in OUT/solves).")
def lesions(n, seed, truth_mesh, truth_sizing, inside, outside, shard, first, out):
    """Solve the phantoms and the held-out lesions with the world's forward model (resumable)."""
    from tqdm import tqdm

    from elastimap.dataset.phantoms import read_phantoms
    from elastimap.errors import UserError

    k, nsh = shard
    if first < 0:
        raise UserError("--first", f"must be >= 0 (got {first})")
    design = lesion_design(n, seed, inside, outside)  # before any folder is made: a bad draw is one line
    cache = os.path.join(out, "solves")
    os.makedirs(cache, exist_ok=True)
    ph = read_phantoms()
    todo = [(float(r["d"]), float(r["h"]), float(r["E"])) for _, r in ph.iterrows()]
    todo += [tuple(map(float, t)) for t in design[: first or n]]
    todo = todo[k::nsh]
    t0 = time.perf_counter()
    for d, h, E in tqdm(todo, desc=f"SYNTHETIC world solves ({world_label(truth_mesh, truth_sizing)})"):
        truth_solve(d, h, E, truth_mesh, cache, truth_sizing)
    click.echo(
        f"{len(todo)} solves (shard {k}/{nsh} of {len(ph)} phantoms + {first or n} lesions) in "
        f"{time.perf_counter() - t0:.0f} s",
        err=True,
    )

"""Benchmark of inference from SYNTHETIC camera frames: image network -> physics fit.

Stage ``lesions`` (no fit needed, run it first): held-out lesions drawn by a Latin hypercube over
the WHOLE design box (d 2-15 mm, the admissible centre depth, E 10-200 kPa log-uniform; own seed,
not the sweep's points) and the nine calibration phantoms, solved by the "world" forward model --
the remeshing solver on ``--truth-mesh`` (default ``default``), a different discretisation than the
fit's forward map -- and kept in the solve store ``OUT/solves``.  Resumable: solved lesions are
read back; ``--shard K/N`` splits the solves between processes, ``--first K`` solves only the
first K lesions of the design (a subset on a costlier world, e.g. ``--truth-mesh fine``).
Everything it makes is SYNTHETIC.

    OMP_NUM_THREADS=1 .venv/bin/python -m elastimap.workflows.benchmarks.frames lesions --n 120 --out runs/frames-bench

Stage ``network``: the start network (the image model's SCG ensemble, the recipe in docs/camera.md,
'Inference') trained on a sweep's design rows, into ``OUT/image-model``.

    .venv/bin/elastimap sweep run --n 160 --mesh tiny --seed 0 --jobs 1 --out runs/sweep-tiny160
    .venv/bin/python -m elastimap.workflows.benchmarks.frames network --sweep runs/sweep-tiny160 --out runs/frames-bench

Stage ``run``: the calibration (the nine phantoms' frames rendered from the world's solves, their
FEM side -- reference press, scale, feature lines -- from the fit's forward map), then per lesion
30 lesion + 30 background frames from the nominal SYNTHETIC camera (own noise seed per lesion) ->
the FEM-equivalent difference image and its per-pixel noise (:mod:`elastimap.camera.deflection`) ->
the image network (``--model``) -> the maximum-likelihood fit on the forward map at ``--fit-mesh``
(:func:`elastimap.camera.infer.refine_estimates`), its model error measured against
``--error-mesh`` (default: the neighbouring coarser level).  ``--correct-mesh LEVEL`` (finer than
``--fit-mesh``) defect-corrects the fit's map by that level at the start of every pass after the
first (``fit_image(forward_fine=...)``); the fit then stands for that level (the calibration's
FEM side is solved on it) and its model error is measured against that level's neighbour.  One
JSON file per lesion in ``OUT/fits`` (resumable; a folder holding lesions of another design --
another ``--seed``, ``--n``, ``--inside`` or ``--outside`` -- is refused; ``--shard K/N`` splits the lesions between
processes; the calibration and the fits are kept per forward map, ``OUT/cal-<tag>.json`` and
``OUT/fits-<tag>``, tag ``<geometry>-<mesh>`` plus ``-corr-<level>`` with ``--correct-mesh`` and
``-err-<level>`` when ``--error-mesh`` is not the default).  Measurement knobs (docs/camera.md, 'Inference'),
each marked in the tag: ``--correct-sizing by_d`` sizes the correcting level and its model-error
level by d (``-corr-<level>-by_d``); ``--fine-mode direct`` makes the passes after the first fit
the correcting level itself instead of correcting the fit's map (``-direct``); ``--max-passes N``
(``-p<N>`` when not 2).  Each record keeps the fit's Gauss–Newton interval beside the reported one, its
Gauss–Newton relative sds and the reported interval's scales (``identify.intervals``).

    OMP_NUM_THREADS=1 .venv/bin/python -m elastimap.workflows.benchmarks.frames run --model M --out runs/frames-bench

``--session drift`` takes each lesion's frames with a camera whose LED powers and vignetting drift
from the calibration's (:func:`session_sensor`); inference keeps the nominal model.

``--inside E`` (give it to ``lesions`` and ``run`` alike) replaces the whole-design draw by a
region-stratified one: the first N lesions of an overdrawn Latin hypercube at which the shipped
map's ``frames`` set calls E identifiable (:func:`draw_lesions`; about 3 % of the design: large,
soft, shallow-to-mid inclusions), so that a quantity identifiable over a small part of the design
is scored on enough lesions.  ``--outside d`` is its mirror: lesions where the map does NOT call d
identifiable (about a quarter of the design: small or deep inclusions), to score the intervals
outside a region on more lesions than a design draw holds.  Neither set is a sample of the design:
report them apart.

Stage ``report``: the table (printed, ``OUT/benchmark.md``), ``OUT/benchmark.json`` and
``OUT/benchmark.png``.  Regions: the shipped identifiability map (``--region-set``, default the
``frames`` set; 10 % threshold) evaluated at the TRUE lesion says whether d, h and E are
identifiable there.  Errors (MRE) are over
the identifiable lesions whose frames show a signal (``no_signal`` lesions report nothing);
coverage is over all lesions.  A second table scores each estimator where it itself reports a
quantity as a number (its own interval within the threshold, decided from the frames alone: what a
user is told to trust).

    .venv/bin/python -m elastimap.workflows.benchmarks.frames report --out runs/frames-bench

Stage ``press`` (a check of the fit's map, writes nothing): at the first lesions, how far the pinned
map's first-order reference press is from the re-solved one, against the map's own discretisation
error (docs/camera.md, 'Inference').

    OMP_NUM_THREADS=1 .venv/bin/python -m elastimap.workflows.benchmarks.frames press --n 5
"""

from .lesions import TRUTH_SEED, draw_lesions, identifiable_at
from .run import LesionInputs, lesion_inputs, run_tags

__all__ = ["TRUTH_SEED", "LesionInputs", "draw_lesions", "identifiable_at", "lesion_inputs", "run_tags"]

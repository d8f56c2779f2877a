"""Replay the forward-model calls a physics fit made: the solver's share of ``infer --refine``.

A trace (JSON list, :data:`REFINE_TRACE`) records, in order, every
:class:`elastimap.solver.morph.MorphedForward` a fit built (``{"new": i, "mesh", "sizing",
"max_references", "cg_rtol"}``), every call it made on one (``{"map": i, "d", "h", "E",
"reference": [d0, h0] | null, "linearise_at": [d, h] | null, "tangent": bool}``) and where each
lesion began (``{"lesion": k}``).  :func:`replay` makes the same calls on the same maps, so the
solver's time per lesion can be measured on each path of ``$ELASTIMAP_PRESSES`` without the fit
(which lives above the sweep) -- ``elastimap sweep timeit -- python -m elastimap.sweep.replay``
times both paths whole-process (docs/sweep.md, 'Benchmark').

:data:`REFINE_TRACE`: the fit ``infer --refine`` runs by default (``coarse`` maps corrected by
``fine``, model error against ``default``; ``elastimap.identify.forward_maps.fit_maps``) on three
SYNTHETIC lesions (d, h, E) = (8, 7, 50), (6, 9, 30), (11, 8, 80) mm/mm/kPa, whose images were
remeshed `default` solves, noise 1 % of the peak, started 10 % / −10 % / +25 % off in d / h / E.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

#: the trace of :func:`replay` the benchmark ships (see the module docstring)
REFINE_TRACE = Path(__file__).with_name("traces") / "refine-3-lesions.json"


def replay(trace: list[dict], lesions: int | None = None) -> list[dict]:
    """Make the calls of ``trace`` (the first ``lesions`` lesions; None: all); returns per lesion
    its solves and CPU and wall seconds (the maps' building is counted in the lesion that built them)."""
    from elastimap.solver.morph import MorphedForward, Reference
    from elastimap.solver.params import Discretisation, SolveParams

    maps: dict[int, MorphedForward] = {}
    out: list[dict] = []
    clock = None
    try:
        for c in trace:
            if "lesion" in c:
                if lesions is not None and len(out) >= lesions:
                    break
                out.append({"lesion": c["lesion"], "solves": 0, "cpu_s": 0.0, "wall_s": 0.0})
                continue
            c0, w0 = time.process_time(), time.perf_counter()
            if "new" in c:
                p = SolveParams(disc=Discretisation(mesh=c["mesh"], sizing=c["sizing"]))
                maps[c["new"]] = MorphedForward(p, max_references=c["max_references"], cg_rtol=c["cg_rtol"])
            else:
                ref = Reference(*c["reference"]) if c["reference"] is not None else None
                at = tuple(c["linearise_at"]) if c["linearise_at"] is not None else None
                call = maps[c["map"]].solve_tangent if c["tangent"] else maps[c["map"]].solve
                call(c["d"], c["h"], c["E"], reference=ref, linearise_at=at)
            clock = out[-1] if out else None
            if clock is not None:
                clock["cpu_s"] += time.process_time() - c0
                clock["wall_s"] += time.perf_counter() - w0
                clock["solves"] += "map" in c
    finally:
        for m in maps.values():
            m.close()
    return out


def main(argv: list[str] | None = None) -> None:
    """``python -m elastimap.sweep.replay [TRACE] [--lesions K]``: replay and print one JSON object
    (per-lesion solves, CPU and wall seconds, and the path of ``$ELASTIMAP_PRESSES``)."""
    import os

    args = list(sys.argv[1:] if argv is None else argv)
    lesions = None
    if "--lesions" in args:
        i = args.index("--lesions")
        lesions = int(args[i + 1])
        del args[i : i + 2]
    path = Path(args[0]) if args else REFINE_TRACE
    res = replay(json.loads(path.read_text()), lesions)
    print(json.dumps({"presses": os.environ.get("ELASTIMAP_PRESSES", "shared"), "lesions": res}))


if __name__ == "__main__":
    main()

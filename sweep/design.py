"""Which samples a sweep runs: a space-filling design over (d, h, E), user tables, phantoms.

A sample is a plain dict ``{"sample_id", "tag", "d", "h", "E"}`` plus optional
overrides of the base solve (``tissue_E``, ``tissue_thickness``).

Ranges: a dict ``{"d": (LO, HI), "h": "auto", "E": (LO, HI, "log")}`` (:func:`check_ranges`);
the command line writes them ``d=LO:HI,h=LO:HI,E=LO:HI[:log|lin]`` (:func:`parse_ranges_text`).
A name left out keeps its default.  Defaults: ``d=2:15`` (mm, uniform), ``h=auto``, ``E=10:200:log``
(kPa, log-uniform: a stiffness ratio matters, not a difference, and the
features change fastest at low E).  ``h`` is the depth of the inclusion centre;
``auto`` (the default) means the whole allowed depth for each d
(:func:`elastimap.solver.params.depth_range`: >= 1 mm cover, >= 2 mm above the chest
wall).  An explicit h range is intersected with the allowed one for each d.

Sampling: a unit-cube design (scipy.stats.qmc Latin hypercube or scrambled
Sobol, seeded) is mapped coordinate-wise: u_d -> d, then u_h -> h inside the
allowed interval *for that d*, u_E -> E.  Every point is valid by construction
and the design stays space-filling in (d, relative depth, E).

Sample ids are stable: ``<design>-s<seed>-<hash6>-<index>`` where the hash
covers the design, seed, ranges, slab thickness (and n for the Latin
hypercube, whose points depend on n; a Sobol sequence's first n points do
not, so a larger Sobol sweep extends a smaller one with the same ids).
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from elastimap.dataset.schema import DESIGN_BOX, TARGETS, THICKNESS, depth_range
from elastimap.errors import UserError

NAMES = TARGETS
DEFAULT_RANGES = "d={:g}:{:g},h=auto,E={:g}:{:g}:log".format(*DESIGN_BOX["d"], *DESIGN_BOX["E"])
DESIGNS = ("lhs", "sobol")
MAX_N = 1_000_000
#: the most inclusion moduli a design geometry may carry (``sweep run --moduli-per-mesh``)
MAX_MODULI_PER_MESH = 64
OVERRIDES = ("tissue_E", "tissue_thickness")


@dataclass(frozen=True)
class Range:
    lo: float | None  # None: automatic (h only)
    hi: float | None
    scale: str = "lin"

    @property
    def auto(self) -> bool:
        return self.lo is None

    def text(self) -> str:
        if self.auto:
            return "auto"
        return f"{self.lo:g}:{self.hi:g}" + (":log" if self.scale == "log" else "")

    def map(self, u: np.ndarray, lo=None, hi=None) -> np.ndarray:
        lo = self.lo if lo is None else lo
        hi = self.hi if hi is None else hi
        if self.scale == "log":
            return np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo)))
        return lo + u * (hi - lo)


def _num(name: str, s) -> float:
    try:
        v = float(s.strip() if isinstance(s, str) else s)
    except (TypeError, ValueError):
        raise UserError("ranges", f"{name}: {s!r} is not a number") from None
    if not math.isfinite(v):
        raise UserError("ranges", f"{name}: {s!r} is not a finite number")
    return v


def parse_ranges_text(text: str | None) -> dict[str, str]:
    """Split the command-line form ``d=2:15,h=auto,E=10:200:log`` into ``{name: "LO:HI[:scale]"}``.

    Names left out are absent (:func:`check_ranges` fills in the defaults); a name given twice
    is an error.
    """
    out: dict[str, str] = {}
    if text is None:
        return out
    if not text.strip():
        raise UserError("ranges", f"expected NAME=LO:HI[,NAME=LO:HI] (names {', '.join(NAMES)}; got '')")
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise UserError("ranges", f"{text!r}: an empty item between commas")
        if "=" not in part:
            raise UserError("ranges", f"{part!r}: expected NAME=LO:HI (names {', '.join(NAMES)})")
        name, spec = (x.strip() for x in part.split("=", 1))
        if name in out:
            raise UserError("ranges", f"{name} is given twice")
        out[name] = spec
    return out


def check_ranges(ranges: dict | None, thickness: float = THICKNESS) -> dict[str, Range]:
    """The design ranges as :class:`Range` objects, defaults filled in, checked against the slab.

    ``ranges`` maps ``d``, ``h``, ``E`` (any of them) to a :class:`Range`, a tuple
    ``(lo, hi)`` or ``(lo, hi, "lin"|"log")``, a string ``"LO:HI[:log]"``, or, for ``h``
    only, ``"auto"``/``None`` (the whole allowed depth for each d).
    """
    out = {name: _range(name, spec) for name, spec in _DEFAULT_SPECS.items()}
    for name, spec in (ranges or {}).items():
        out[name] = _range(name, spec)
    d, h = out["d"], out["h"]
    if d.lo <= 0:
        raise UserError("ranges", f"d must be > 0 mm (got {d.text()})")
    if out["E"].lo <= 0:
        raise UserError("ranges", f"E must be > 0 kPa (got {out['E'].text()})")
    lo, hi = depth_range(d.hi, thickness)
    if lo > hi:
        dmax = thickness - 3.0
        raise UserError(
            "ranges",
            f"d up to {d.hi:g} mm does not fit in the {thickness:g} mm slab (1 mm cover, 2 mm floor: d <= {dmax:g} mm)",
        )
    if not h.auto:
        # the allowed interval shrinks as d grows: the largest d is the binding case
        if max(h.lo, lo) > min(h.hi, hi):
            raise UserError(
                "ranges",
                f"h={h.text()} mm leaves no valid depth for d = {d.hi:g} mm "
                f"(allowed centre depth [{lo:g}, {hi:g}] mm); use h=auto or a wider range",
            )
    return out


def parse_ranges(text: str | None, thickness: float = THICKNESS) -> dict[str, Range]:
    """Parse ``d=2:15,h=auto,E=10:200:log`` (names may be left out) and check it against the slab."""
    return check_ranges(parse_ranges_text(text), thickness)


def _range(name: str, spec) -> Range:
    if name not in NAMES:
        raise UserError("ranges", f"unknown parameter {name!r} (known: {', '.join(NAMES)})")
    if isinstance(spec, Range):
        spec = (spec.lo, spec.hi, spec.scale) if not spec.auto else None
    if spec is None or spec == "auto":
        if name != "h":
            raise UserError("ranges", f"only h can be 'auto' (got {name}=auto)")
        return Range(None, None)
    if isinstance(spec, str):
        bits = spec.split(":")
    elif isinstance(spec, (tuple, list)):
        bits = list(spec)
    else:
        raise UserError("ranges", f"{name}: expected (LO, HI), (LO, HI, scale) or 'LO:HI[:log]' (got {spec!r})")
    scale = "lin"
    if len(bits) == 3:
        scale = str(bits.pop()).strip()
        if scale not in ("lin", "log"):
            raise UserError("ranges", f"{name}: scale must be lin or log (got {scale!r})")
    if len(bits) != 2:
        raise UserError("ranges", f"{name}={spec!r}: expected LO:HI or LO:HI:log")
    lo, hi = _num(name, bits[0]), _num(name, bits[1])
    if not lo < hi:
        raise UserError("ranges", f"{name}: LO must be < HI (got {lo:g}:{hi:g})")
    if scale == "log" and lo <= 0:
        raise UserError("ranges", f"{name}: a log range needs LO > 0 (got {lo:g})")
    return Range(lo, hi, scale)


_DEFAULT_SPECS = parse_ranges_text(DEFAULT_RANGES)


def ranges_text(ranges: dict[str, Range]) -> str:
    return ",".join(f"{k}={ranges[k].text()}" for k in NAMES)


def check_n(n: int) -> int:
    if n is None or n < 0 or n > MAX_N:
        raise UserError("n", f"must be an integer in [0, {MAX_N}] (got {n})")
    return int(n)


def design_points(
    n: int, design: str, seed: int, ranges: dict[str, Range], thickness: float = THICKNESS, moduli_per_mesh: int = 1
) -> list[dict]:
    """``n`` samples of the space-filling design, with stable ids.

    ``moduli_per_mesh`` k > 1: ⌈n / k⌉ geometries (d, h) of the design, each with k inclusion moduli
    (the last with what is left of n), one in each of its c equal strata of the E range (the design's
    third coordinate u_E gives the geometry's offset in its stratum: E_j = E((j + u_E) / c),
    j = 0 … c−1); so E stays uniform over its range (in log E by default), and the samples of a
    geometry share its mesh, its model and its reference press (:func:`elastimap.sweep.jobs.run_group`)."""
    check_n(n)
    k = moduli_per_mesh
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= MAX_MODULI_PER_MESH:
        raise UserError("moduli-per-mesh", f"must be an integer in [1, {MAX_MODULI_PER_MESH}] (got {k!r})")
    if design not in DESIGNS:
        raise UserError("design", f"must be one of {', '.join(DESIGNS)} (got {design!r})")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UserError("seed", f"must be an integer >= 0 (got {seed!r})")
    if n == 0:
        return []
    from scipy.stats import qmc

    rng = np.random.default_rng(seed)
    m = -(-n // k)  # geometries
    if design == "lhs":
        u = qmc.LatinHypercube(d=3, rng=rng).random(m)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "balance properties" warning for n not a power of 2
            u = qmc.Sobol(d=3, scramble=True, rng=rng).random(m)
    if k > 1:  # each geometry c times (k, the last what is left), its moduli one in each stratum of E
        count = np.full(m, k)
        count[-1] = n - k * (m - 1)
        g = np.repeat(np.arange(m), count)
        u = u[g]
        u[:, 2] = (np.concatenate([np.arange(c) for c in count]) + u[:, 2]) / count[g]
    d = ranges["d"].map(u[:, 0])
    lo, hi = depth_range(d, thickness)
    h_rng = ranges["h"]
    if not h_rng.auto:
        lo, hi = np.maximum(lo, h_rng.lo), np.minimum(hi, h_rng.hi)
    h = (h_rng if not h_rng.auto else Range(0, 1)).map(u[:, 1], lo, hi)
    E = ranges["E"].map(u[:, 2])
    key = {"design": design, "seed": seed, "ranges": ranges_text(ranges), "thickness": thickness}
    if design == "lhs":
        key["n"] = n
    if k > 1:
        key["moduli_per_mesh"] = k
    tag = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:6]
    width = max(5, len(str(n - 1)))
    return [
        {
            "sample_id": f"{design}-s{seed}-{tag}-{i:0{width}d}",
            "tag": "design",
            "d": round(float(d[i]), 6),
            "h": round(float(h[i]), 6),
            "E": round(float(E[i]), 6),
        }
        for i in range(n)
    ]


def load_samples(path: str) -> list[dict]:
    """Rows of a user table (CSV or Parquet): columns d, h, E; optional sample_id, tissue_E, tissue_thickness."""
    import pandas as pd

    p = Path(path)
    if not p.is_file():
        raise UserError("samples", f"{path} does not exist or is not a file")
    try:
        if p.suffix.lower() in (".parquet", ".pq"):
            df = pd.read_parquet(p)
        elif p.suffix.lower() in (".csv", ".txt"):
            df = pd.read_csv(p, comment="#", skipinitialspace=True)
        else:
            raise UserError("samples", f"{path}: expected a .csv or .parquet file")
    except UserError:
        raise
    except Exception as exc:
        raise UserError(
            "samples", f"{path} cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    cols = [str(c).strip() for c in df.columns]
    df.columns = cols
    if "id" in cols and "sample_id" not in cols:
        df = df.rename(columns={"id": "sample_id"})
        cols = list(df.columns)
    missing = [c for c in NAMES if c not in cols]
    if missing:
        raise UserError("samples", f"{path} lacks column(s) {', '.join(missing)} (has: {', '.join(cols) or 'none'})")
    allowed = {*NAMES, "sample_id", *OVERRIDES}
    unknown = [c for c in cols if c not in allowed]
    if unknown:
        raise UserError(
            "samples", f"{path}: unknown column(s) {', '.join(unknown)} (allowed: {', '.join(sorted(allowed))})"
        )
    if len(df) == 0:
        raise UserError("samples", f"{path} has no rows")
    out = []
    for i, r in enumerate(df.to_dict("records")):
        line = f"{path} row {i + 1}"
        s = {"tag": "user"}
        for c in (*NAMES, *OVERRIDES):
            if c not in r:
                continue
            try:
                v = float(r[c])
            except (TypeError, ValueError):
                raise UserError("samples", f"{line}: {c}={r[c]!r} is not a number") from None
            if not math.isfinite(v):
                raise UserError("samples", f"{line}: {c} is missing or not finite")
            s[c] = v
        sid = r.get("sample_id")
        if sid is None or (isinstance(sid, float) and math.isnan(sid)) or str(sid).strip() == "":
            key = json.dumps({c: s[c] for c in (*NAMES, *OVERRIDES) if c in s}, sort_keys=True)
            sid = "user-" + hashlib.sha1(key.encode()).hexdigest()[:10]
        s["sample_id"] = str(sid).strip()
        out.append(s)
    from collections import Counter

    dup = sorted(i for i, c in Counter(s["sample_id"] for s in out).items() if c > 1)
    if dup:
        raise UserError(
            "samples", f"{path}: duplicate sample id(s) {', '.join(dup[:5])} (identical rows, or a repeated sample_id)"
        )
    return out

"""``elastimap sweep timeit -- COMMAND``: a whole command timed on the presses before and as shipped.

Every :class:`elastimap.solver.fem.Model` reads how its presses share their work from
``$ELASTIMAP_PRESSES`` (``separate``: each press assembled, reduced and factorised for itself, the
path before; ``shared``: the path as shipped; :func:`elastimap.solver.fem.default_presses`), so any
command that solves -- a single ``solve``, ``infer --refine`` (morphed maps), ``gap diagnose``
(batched variants) -- runs on either path without a change on its side.  :func:`timeit` runs the
command once per path in turn, ``repeat`` rounds (interleaved, so the load of a shared machine
falls on both alike), and reports per path the median wall time, the median CPU time of the
command and its children (user + system, from ``wait4``), the largest resident memory, the ratios
to the first path and, where the command prints one JSON object (``solve --json``), the largest
relative difference of its features and force from the first path's (docs/sweep.md, 'Benchmark').
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import time

from elastimap.errors import UserError

#: the values of ``$ELASTIMAP_PRESSES`` timed, the baseline first
PRESSES = ("separate", "shared")
#: the numbers of a command's JSON answer compared between the paths
COMPARED = ("O1", "O2", "O3", "force")


def run_once(command: list[str], presses: str) -> dict:
    """One run of ``command`` with ``ELASTIMAP_PRESSES=presses``: wall and CPU seconds, peak MiB,
    exit code and the stdout's JSON object (None when stdout is not one)."""
    env = dict(os.environ, ELASTIMAP_PRESSES=presses)
    t0 = time.perf_counter()
    try:
        proc = subprocess.Popen(command, stdout=subprocess.PIPE, env=env)
    except OSError as exc:
        raise UserError("command", f"cannot run {command[0]!r}: {exc.strerror}") from None
    out = proc.stdout.read()
    _pid, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    try:
        answer = json.loads(out)
    except ValueError:
        answer = None
    return {
        "presses": presses,
        "rc": proc.returncode,
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "peak_MiB": ru.ru_maxrss / 1024.0,
        "answer": answer if isinstance(answer, dict) else None,
    }


def timeit(command: list[str], repeat: int = 3, paths: tuple[str, ...] = PRESSES) -> dict:
    """``repeat`` interleaved rounds of ``command`` on each of ``paths``; the summary (see the
    module docstring), with every run under ``runs``.  Raises :class:`UserError` when a run fails."""
    if not command:
        raise UserError("command", "give the command to time after '--'")
    if not 1 <= repeat <= 50:
        raise UserError("repeat", f"must be an integer in [1, 50] (got {repeat})")
    runs = []
    for _ in range(repeat):
        for p in paths:
            r = run_once(command, p)
            if r["rc"] != 0:
                raise UserError("command", f"exited with {r['rc']} under ELASTIMAP_PRESSES={p}")
            runs.append(r)
    load = os.getloadavg()[0]
    summary = {}
    for p in paths:
        mine = [r for r in runs if r["presses"] == p]
        summary[p] = {
            "wall_s": statistics.median(r["wall_s"] for r in mine),
            "cpu_s": statistics.median(r["cpu_s"] for r in mine),
            "peak_MiB": max(r["peak_MiB"] for r in mine),
        }
    base = summary[paths[0]]
    for p in paths[1:]:
        s = summary[p]
        s["wall_ratio"] = base["wall_s"] / s["wall_s"]
        s["cpu_ratio"] = base["cpu_s"] / s["cpu_s"]
        s["max_rel_dev"] = _deviation(runs, paths[0], p)
    return {"command": command, "repeat": repeat, "load_1min": load, "paths": summary, "runs": runs}


def _deviation(runs: list[dict], base: str, other: str) -> dict | None:
    """Largest relative difference of :data:`COMPARED` between the paths' JSON answers (None
    when the command answers no JSON object)."""
    a = [r["answer"] for r in runs if r["presses"] == base]
    b = [r["answer"] for r in runs if r["presses"] == other]
    if not a or not b or a[0] is None or b[0] is None:
        return None
    out = {}
    for k in COMPARED:
        x, y = a[0].get(k), b[0].get(k)
        if isinstance(x, (int, float)) and isinstance(y, (int, float)):
            out[k] = abs(y - x) / max(abs(x), 1e-300)
    return out


def report(res: dict) -> str:
    """Markdown table of :func:`timeit`'s summary."""
    lines = [
        f"`{' '.join(res['command'])}`, median of {res['repeat']} interleaved runs, "
        f"load average {res['load_1min']:.1f}",
        "",
        "| ELASTIMAP_PRESSES | wall s | CPU s (user+sys) | peak MiB | wall ratio | CPU ratio | largest rel. dev. |",
        "|---|---|---|---|---|---|---|",
    ]
    for p, s in res["paths"].items():
        dev = s.get("max_rel_dev")
        dev_txt = ", ".join(f"{k} {v:.1e}" for k, v in dev.items()) if dev else "—"
        ratios = (f"{s['wall_ratio']:.2f}×", f"{s['cpu_ratio']:.2f}×") if "wall_ratio" in s else ("—", "—")
        lines.append(
            f"| {p} | {s['wall_s']:.2f} | {s['cpu_s']:.2f} | {s['peak_MiB']:.0f} | {ratios[0]} | {ratios[1]} | "
            f"{dev_txt if 'wall_ratio' in s else '—'} |"
        )
    return "\n".join(lines)

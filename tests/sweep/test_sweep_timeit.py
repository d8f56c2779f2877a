"""``sweep timeit``: a whole command on each path of ``$ELASTIMAP_PRESSES``, interleaved, with
the ratios and the JSON answer's deviation; ``python -m elastimap.sweep.replay``: a fit's solver
calls replayed (real tiny-mesh solves)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from elastimap.errors import UserError
from elastimap.sweep.replay import REFINE_TRACE, replay
from elastimap.sweep.timeit import report, timeit

#: a stand-in command whose answer depends on the path it runs on
ECHO = [
    sys.executable,
    "-c",
    "import json, os; s = os.environ['ELASTIMAP_PRESSES'] == 'shared'; "
    "print(json.dumps({'O1': 2.0 + 1e-6 * s, 'O2': 3.0, 'force': 5.0, 'other': 'x'}))",
]


def test_timeit_runs_each_path_in_turn_and_compares_the_answers():
    res = timeit(ECHO, repeat=2)
    assert [r["presses"] for r in res["runs"]] == ["separate", "shared", "separate", "shared"]
    shared = res["paths"]["shared"]
    assert shared["max_rel_dev"]["O1"] == pytest.approx(5e-7)
    assert shared["max_rel_dev"]["O2"] == 0.0 and "other" not in shared["max_rel_dev"]
    assert shared["cpu_ratio"] > 0 and shared["wall_ratio"] > 0
    assert all(r["cpu_s"] > 0 for r in res["runs"])
    text = report(res)
    assert "| separate |" in text and "| shared |" in text and "O1 5.0e-07" in text


def test_timeit_refuses_a_failing_command_and_bad_repeat():
    with pytest.raises(UserError) as err:
        timeit([sys.executable, "-c", "raise SystemExit(3)"], repeat=1)
    assert err.value.param == "command" and "exited with 3" in err.value.message
    with pytest.raises(UserError) as err:
        timeit(ECHO, repeat=0)
    assert err.value.param == "repeat"
    with pytest.raises(UserError):
        timeit([], repeat=1)


def test_timeit_command_line():
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.sweep.cli", "timeit", "--repeat", "1", "--", *ECHO],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert "| shared |" in r.stdout and "median of 1 interleaved runs" in r.stdout


def test_replay_makes_the_traced_calls_per_lesion(tmp_path):
    trace = [
        {"new": 0, "mesh": "tiny", "sizing": "fixed", "max_references": 2, "cg_rtol": 1e-9},
        {"lesion": 0},
        {"map": 0, "d": 8.0, "h": 7.0, "E": 50.0, "reference": [8.0, 7.0], "linearise_at": None, "tangent": False},
        {"map": 0, "d": 8.2, "h": 7.1, "E": 45.0, "reference": [8.0, 7.0], "linearise_at": [8.0, 7.0], "tangent": True},
        {"lesion": 1},
        {"map": 0, "d": 7.5, "h": 7.0, "E": 30.0, "reference": [8.0, 7.0], "linearise_at": None, "tangent": False},
    ]
    res = replay(trace)
    assert [r["solves"] for r in res] == [2, 1]
    assert all(r["cpu_s"] > 0 and r["wall_s"] > 0 for r in res)
    assert [r["solves"] for r in replay(trace, lesions=1)] == [2]
    # the shipped trace: the fit infer --refine runs, three lesions
    shipped = json.loads(REFINE_TRACE.read_text())
    assert sum("lesion" in c for c in shipped) == 3
    assert {c["mesh"] for c in shipped if "new" in c} == {"coarse", "default", "fine"}

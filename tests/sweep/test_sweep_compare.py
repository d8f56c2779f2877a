"""``sweep bench --compare``: the same sample list by each press factorised for itself and by the
shipped forward model, both timed in one command, with the ratio and the feature deviation
(real tiny-mesh solves)."""

from __future__ import annotations

import pytest
from sweep_helpers import run_sweep

from elastimap.dataset import io
from elastimap.errors import UserError
from elastimap.sweep.bench import COMPARED, compare, feature_deviation


def test_compare_command_times_both_paths_and_their_features_agree(tmp_path):
    out = tmp_path / "cmp"
    r = run_sweep(
        ["bench", "--compare", "--n", "3", "--mesh", "tiny", "--jobs-list", "1", "--out", str(out)], timeout=600
    )
    assert r.returncode == 0, r.stderr
    assert "shared vs separate" in r.stdout and "less worker CPU per sample" in r.stdout
    for path in ("separate", "shared"):
        assert len(io.read_samples(out / f"{path}-jobs1")) == 3
    dev = feature_deviation(out / "separate-jobs1", out / "shared-jobs1")
    assert dev["samples"] == 3
    assert all(dev[k] < 1e-4 for k in COMPARED), dev
    assert "features over 3 samples" in r.stdout


def test_compare_refuses_the_synthetic_solver_and_a_used_out(tmp_path):
    from elastimap.sweep.jobs import resolve_solver

    with pytest.raises(UserError) as err:
        compare([1], n=2, mesh="tiny", solver=resolve_solver("synthetic"))
    assert err.value.param == "solver"
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "f").write_text("")
    with pytest.raises(UserError) as err:
        compare([1], out=str(tmp_path / "x"), n=2, mesh="tiny")
    assert err.value.param == "out"


def test_compare_with_the_morphed_path_times_it_and_reports_its_deviation(tmp_path):
    out = tmp_path / "cmp"
    r = run_sweep(
        [
            "bench",
            "--compare",
            "--paths",
            "shared,morph",
            "--n",
            "2",
            "--mesh",
            "tiny",
            "--jobs-list",
            "1",
            "--out",
            str(out),
        ],
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    assert "morph vs shared" in r.stdout and "morph = shared presses/morph/by_d" in r.stdout
    assert not (out / "separate-jobs1").exists()
    shared, morph = (io.read_samples(out / f"{p}-jobs1") for p in ("shared", "morph"))
    # the same sample ids (the design does not depend on the forward model) ...
    assert sorted(shared["sample_id"]) == sorted(morph["sample_id"])
    # ... solved by a different discretisation: close, not equal
    dev = feature_deviation(out / "shared-jobs1", out / "morph-jobs1")
    assert dev["samples"] == 2
    assert 0 < dev["O2"] < 0.2, dev
    assert dev["mean_O2"] <= dev["O2"]


@pytest.mark.parametrize("text", ["shared", "shared,shared", "separate,remesh", ""])
def test_paths_must_be_two_or_more_distinct_known_names(text):
    from elastimap.sweep.bench import parse_paths

    with pytest.raises(UserError) as err:
        parse_paths(text)
    assert err.value.param == "paths"
    assert parse_paths("separate, morph") == ("separate", "morph")


def test_bad_paths_is_a_one_line_error_and_writes_nothing(tmp_path):
    out = tmp_path / "cmp"
    r = run_sweep(["bench", "--compare", "--paths", "shared,fast", "--n", "2", "--mesh", "tiny", "--out", str(out)])
    assert r.returncode == 2
    assert "paths" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()

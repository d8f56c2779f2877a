"""No command deletes its own input data, and a run whose writes fail keeps its finished result.

Before: ``train --data X --out X --overwrite`` deleted the sweep X (the finished run replaced the
folder whole); a full disk during ``train`` discarded the whole run with a traceback although
docs/errors.md promises a fallback copy.
"""

from __future__ import annotations

import errno
import re
import tempfile
from pathlib import Path

import pytest
from test_bad_inputs import assert_refused, invoke, make_dataset, snapshot

from elastimap import outputs

TRAIN = ["--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress", "--algo", "scg"]


@pytest.mark.parametrize("where", ["same", "parent"])
def test_train_never_replaces_its_own_data(tmp_path, where):
    ds = make_dataset(tmp_path / "runs" / "ds", n=40)
    out = ds if where == "same" else tmp_path / "runs"
    before = snapshot(tmp_path)
    code, o, e = invoke("train", ["--data", str(ds), *TRAIN, "--out", str(out), "--overwrite"])
    assert_refused(code, o, e, ("--out",))
    assert "input" in e and snapshot(tmp_path) == before


def test_train_on_a_full_disk_keeps_the_finished_run(tmp_path, monkeypatch):
    work, spare = tmp_path / "work", tmp_path / "spare"
    work.mkdir()
    spare.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spare))
    real = outputs._fsync_tree

    def full_disk(root):  # the disk that holds --out is full; $TMPDIR is not
        if Path(root).parent == work:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(root)

    monkeypatch.setattr(outputs, "_fsync_tree", full_disk)
    code, o, e = invoke("train", ["--synthetic", "30", *TRAIN, "--out", str(work / "tr")])
    assert code == 2 and "Traceback" not in e, e
    line = e.strip().splitlines()[-1]
    assert "No space left" in line and "--out" in line
    fb = Path(re.search(r"saved to (\S+) instead", line).group(1))
    assert fb.parent == spare
    assert {"results.csv", "results.md", "run.json", "model-scg"} <= {p.name for p in fb.iterdir()}
    assert list(work.iterdir()) == []  # nothing half-written left where --out was


class StepRan(BaseException):
    """The demo started a pipeline step before its inputs were checked."""


@pytest.fixture
def no_steps(monkeypatch):
    import elastimap.cli

    def trap(title, argv):
        raise StepRan(title)

    monkeypatch.setattr(elastimap.cli, "_step", trap)


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--jobs", "99999"], "--jobs"),
        (["--n", "0"], "--n"),
        (["--out", "{T}/user"], "--out"),  # a folder with the user's own train/
        (["--out", "{T}/sweep"], "--out"),  # somebody's sweep
    ],
    ids=["jobs", "n", "user-train", "sweep"],
)
def test_demo_checks_first_and_only_reruns_in_its_own_folder(args, flag, tmp_path, monkeypatch, no_steps):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "user" / "train").mkdir(parents=True)
    (tmp_path / "user" / "train" / "model.txt").write_text("the user's own")
    make_dataset(tmp_path / "sweep", n=10)
    before = snapshot(tmp_path)
    code, o, e = invoke("elastimap", ["demo", *[a.replace("{T}", str(tmp_path)) for a in args]])
    assert_refused(code, o, e, (flag,))
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- gap
GSYN = ["--backend", "toy", "--cache", "none", "--n", "4", "--frames", "2", "--mesh", "tiny", "--no-progress"]
GDIAG = ["diagnose", "--backend", "toy", "--cache", "none", "--no-inverse", "--no-progress"]


def test_a_killed_diagnosis_leaves_the_earlier_report_whole(tmp_path, monkeypatch):
    from elastimap.gap import report

    assert invoke("gap", ["synth", *GSYN, "--out", str(tmp_path / "S")])[0] == 0
    dg = tmp_path / "dg"
    code, _, e = invoke("gap", [*GDIAG, "--measured", str(tmp_path / "S"), "--out", str(dg)])
    assert code == 0, e
    before = snapshot(dg)
    real = report.write

    def killed(res, out):  # the kill comes after the new diagnosis.json, before the rest
        real(res, out)
        (Path(out) / "report.md").unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "write", killed)
    code, _, e = invoke("gap", [*GDIAG, "--measured", str(tmp_path / "S"), "--out", str(dg), "--seed", "1"])
    assert code == 130
    assert snapshot(dg) == before  # the first run's report, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["S", "dg"]  # no staging folder left


def test_diagnose_never_replaces_a_folder_with_other_files(tmp_path):
    assert invoke("gap", ["synth", *GSYN, "--out", str(tmp_path / "S")])[0] == 0
    before = snapshot(tmp_path)
    for out in (tmp_path / "S", tmp_path):
        code, o, e = invoke("gap", [*GDIAG, "--measured", str(tmp_path / "S"), "--out", str(out)])
        assert_refused(code, o, e, ("--out",))
    assert snapshot(tmp_path) == before


def test_gap_synth_on_a_full_disk_keeps_the_set(tmp_path, monkeypatch):
    work, spare = tmp_path / "work", tmp_path / "spare"
    work.mkdir()
    spare.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spare))
    real = outputs._fsync_tree

    def full_disk(root):
        if Path(root).parent == work:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(root)

    monkeypatch.setattr(outputs, "_fsync_tree", full_disk)
    code, o, e = invoke("gap", ["synth", *GSYN, "--out", str(work / "S")])
    assert code == 2 and "Traceback" not in e and len(e.strip().splitlines()) == 1, e
    fb = Path(re.search(r"saved to (\S+) instead", e).group(1))
    assert {"measured.csv", "measured.json", "SEALED_truth.json"} <= {p.name for p in fb.iterdir()}
    assert list(work.iterdir()) == []

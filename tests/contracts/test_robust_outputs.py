"""One writer for every output (:mod:`elastimap.outputs`): whole files, whole folders, a fallback.

What a full disk, a kill mid-write or a second run did before: an existing calibration JSON or
``dataset export`` CSV was replaced by a truncated 4 KB file; a folder left half-written or
mixed; a staging folder of a killed run stayed for ever.  Here a "full disk" is a write that
fails with ENOSPC part-way (in-process), or a file-size limit (``RLIMIT_FSIZE``) on a real
command in a subprocess.
"""

from __future__ import annotations

import errno
import re
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from test_bad_inputs import make_dataset

from elastimap.errors import UserError
from elastimap.outputs import publish_dir, staged_dir, write_dir, write_or_fallback, write_text


def _full_disk_in(folder: Path, payload: bytes):
    """A writer that fails like a full disk (ENOSPC after 4 KB) inside ``folder``, works elsewhere."""

    def write(name: str) -> None:
        with open(name, "wb") as fh:
            if Path(name).resolve().parent == folder.resolve():
                fh.write(payload[:4096])
                fh.flush()
                raise OSError(errno.ENOSPC, "No space left on device")
            fh.write(payload)

    return write


def test_full_disk_keeps_the_old_file_and_saves_the_result(tmp_path):
    target = tmp_path / "cal.json"
    target.write_text("the old calibration\n")
    payload = b"x" * 20000
    with pytest.raises(UserError, match="No space left") as ei:
        write_or_fallback(_full_disk_in(tmp_path, payload), target, "--out")
    assert target.read_text() == "the old calibration\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]  # no partial sibling left
    fb = Path(re.search(r"saved to (\S+) instead", str(ei.value)).group(1))
    try:
        assert fb.read_bytes() == payload and fb.suffix == ".json"
    finally:
        fb.unlink()


def test_write_goes_through_a_symlink_and_a_dead_link_is_refused_before(tmp_path):
    from elastimap.outputs import check_out_file

    real = tmp_path / "real.txt"
    real.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(real)
    write_text(link, "new", "--out")
    assert link.is_symlink() and real.read_text() == "new"
    loop = tmp_path / "loop.png"
    loop.symlink_to(loop)
    with pytest.raises(UserError, match="leads nowhere"):
        check_out_file(loop, "--image")


def test_folder_replaced_whole_or_not_at_all(tmp_path):
    final = tmp_path / "report"
    final.mkdir()
    (final / "old.md").write_text("run 1")
    with pytest.raises(UserError, match="No space left"):
        with staged_dir(final, "--out", overwrite=True) as tmp:
            (tmp / "report.md").write_text("run 2, half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert [p.name for p in final.iterdir()] == ["old.md"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]
    with staged_dir(final, "--out", overwrite=True) as tmp:
        (tmp / "report.md").write_text("run 2")
    assert [p.name for p in final.iterdir()] == ["report.md"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_publish_dir_exchanges_folders(tmp_path):
    final, new = tmp_path / "out", tmp_path / ".out.x.partial"
    final.mkdir()
    (final / "a").write_text("old")
    new.mkdir()
    (new / "b").write_text("new")
    publish_dir(new, final)
    assert [p.name for p in final.iterdir()] == ["b"] and not new.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_write_dir_falls_back_when_the_disk_is_full(tmp_path):
    final = tmp_path / "run"

    def write(folder: Path) -> None:
        (folder / "model.json").write_text("{}")
        if folder.parent == tmp_path:
            raise OSError(errno.ENOSPC, "No space left on device")
        (folder / "table.md").write_text("| a |")

    with pytest.raises(UserError, match="saved to") as ei:
        write_dir(final, write, "--out")
    assert not final.exists() and list(tmp_path.iterdir()) == []
    fb = Path(re.search(r"saved to (\S+) instead", str(ei.value)).group(1))
    try:
        assert sorted(p.name for p in fb.iterdir()) == ["model.json", "table.md"]
    finally:
        import shutil

        shutil.rmtree(fb)


def test_stale_staging_folders_of_killed_runs_are_removed(tmp_path):
    final = tmp_path / "run"
    stale = tmp_path / ".run.abc123.partial"
    stale.mkdir()
    (stale / "half.pt").write_text("x")
    live = tmp_path / ".run.live01.partial"
    live.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDONLY); "
            "fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)",
            str(live),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with staged_dir(final, "--out") as tmp:
            (tmp / "x").write_text("1")
        assert not stale.exists() and live.exists()
    finally:
        holder.kill()
        holder.wait()


def _limit_file_size(nbytes: int):
    def pre():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))

    return pre


def test_export_on_a_full_disk_keeps_the_existing_csv(tmp_path):
    ds = make_dataset(tmp_path / "ds", n=60)
    csv = tmp_path / "export.csv"
    csv.write_text("the user's earlier export\n")
    p = subprocess.run(
        [sys.executable, "-m", "elastimap.dataset.cli", "export", str(ds), "--csv", str(csv)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        preexec_fn=_limit_file_size(4096),
    )
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert csv.read_text() == "the user's earlier export\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["ds", "export.csv"]

"""Where results go: output locations checked before any work, folders published whole.

Every command checks its output locations with these functions *before* it computes
anything, so a typo in ``--out`` costs a second, not a sweep:

* :func:`check_out_file` -- a file to write: its folder must exist and be writable and the
  path must not be a folder;
* :func:`check_out_dir` -- a folder to fill: not a file, writable (parents are created), and,
  unless the caller allows it, empty or replaced only with ``overwrite``;
* :func:`staged_dir` -- a folder that must hold exactly one run's results: the run writes
  into a hidden temporary sibling, which replaces the folder whole when the run succeeds
  (and is removed when it fails), so no mix of two runs and no half-written folder remains;
* :func:`write_or_fallback` -- when writing still fails at the end (disk full, permissions
  changed), the finished result is written to a temporary file whose path the error names.

Refusals are :class:`elastimap.errors.UserError` naming the parameter; nothing is created
on disk by a check.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import UserError

__all__ = ["check_out_file", "check_out_dir", "staged_dir", "publish_dir", "write_or_fallback", "is_empty_dir"]


def _nearest_existing(p: Path) -> Path:
    p = Path(os.path.abspath(p))
    while not os.path.lexists(p):
        p = p.parent
    return p


def _check_creatable(p: Path, param: str) -> None:
    """``p`` does not exist: its nearest existing ancestor must be a writable folder."""
    anc = _nearest_existing(p)
    if not anc.is_dir():
        raise UserError(param, f"cannot create {p}: {anc} is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise UserError(param, f"cannot create {p}: no write permission in {anc}")


def is_empty_dir(p: str | os.PathLike) -> bool:
    p = Path(p)
    return p.is_dir() and not any(p.iterdir())


def check_out_file(path: str | os.PathLike, param: str, *, create_parents: bool = False) -> Path:
    """A file about to be written: not a folder, in an existing folder we may write in
    (with ``create_parents``: in a folder the writer may create).

    An existing file is allowed (the caller decides whether replacing it is right)."""
    p = Path(path)
    if p.is_dir():
        raise UserError(param, f"{p} is a folder; give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if create_parents and not os.path.lexists(parent):
        _check_creatable(parent, param)
        return p
    if not parent.is_dir():
        what = "is a file, not a folder" if parent.exists() else "does not exist"
        raise UserError(param, f"cannot write {p}: the folder {parent} {what}")
    if not os.access(parent, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise UserError(param, f"cannot write {p}: no write permission")
    return p


def check_out_dir(
    path: str | os.PathLike,
    param: str,
    *,
    overwrite: bool = False,
    allow_existing: bool = False,
    hint: str = "--overwrite",
) -> Path:
    """A folder about to be filled.

    Refused: a file at ``path``; a folder we cannot write in (or create); a folder that
    already holds files, unless ``overwrite`` (the caller replaces it whole) or
    ``allow_existing`` (the caller adds to it, e.g. a resumable sweep)."""
    p = Path(path)
    if os.path.lexists(p) and not p.is_dir():
        raise UserError(param, f"{p} is a file, not a folder")
    if p.is_dir():
        if not os.access(p, os.W_OK | os.X_OK):
            raise UserError(param, f"cannot write in {p}: no write permission")
        if not (overwrite or allow_existing or is_empty_dir(p)):
            raise UserError(param, f"{p} already holds files; give {hint} to replace it, or choose another folder")
        if overwrite and not os.access(p.parent if str(p.parent) else Path("."), os.W_OK | os.X_OK):
            raise UserError(param, f"cannot replace {p}: no write permission in {p.parent}")
    else:
        _check_creatable(p, param)
    return p


def publish_dir(tmp: Path, final: Path, param: str = "out") -> Path:
    """Move a finished temporary folder to ``final``, replacing what was there as a whole."""
    old = None
    try:
        if os.path.lexists(final):
            old = final.with_name(f".{final.name}.old-{uuid.uuid4().hex[:8]}")
            os.replace(final, old)
        os.replace(tmp, final)
    except OSError as exc:
        if old is not None and not os.path.lexists(final):
            try:
                os.replace(old, final)
                old = None
            except OSError:
                pass
        raise UserError(
            param, f"could not move the finished result to {final} ({exc.strerror or exc}); it is kept in {tmp}"
        ) from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return final


@contextmanager
def staged_dir(final: str | os.PathLike, param: str = "out", *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary sibling of ``final`` to write one run's results into.

    On success it replaces ``final`` whole (an earlier folder is removed only after the new one
    is complete); on any error it is removed and ``final`` is untouched.  ``final`` is checked
    first (:func:`check_out_dir`): an existing non-empty folder needs ``overwrite``."""
    final = Path(final)
    check_out_dir(final, param, overwrite=overwrite)
    parent = final.parent if str(final.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    publish_dir(tmp, final, param)


def write_or_fallback(write: Callable[[str], object], path: str | os.PathLike, param: str) -> Path:
    """``write(path)``; if that fails with an OS error, ``write`` to a temporary file instead and
    raise :class:`UserError` naming both, so a finished result is never thrown away."""
    p = Path(path)
    try:
        write(str(p))
        return p
    except OSError as exc:
        fd, fb = tempfile.mkstemp(prefix=f"elastimap-{p.stem}-", suffix=p.suffix)
        os.close(fd)
        try:
            write(fb)
        except OSError:
            raise UserError(param, f"cannot write {p} ({exc.strerror or exc}), nor a fallback copy") from None
        raise UserError(
            param, f"cannot write {p} ({exc.strerror or exc}); the result was saved to {fb} instead"
        ) from None

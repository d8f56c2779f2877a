"""Where results go: output locations checked before any work, every file and folder written whole.

Every command checks its output locations with these functions *before* it computes
anything, so a typo in ``--out`` costs a second, not a sweep:

* :func:`check_out_file` -- a file to write: its folder must exist and be writable and the
  path must not be a folder (nor a symbolic link that leads nowhere);
* :func:`check_out_dir` -- a folder to fill: not a file, writable (parents are created), and,
  unless the caller allows it, empty or replaced only with ``overwrite``;
* :func:`check_inputs_kept` -- an output folder that is, or holds, one of the command's inputs
  is refused (replacing it would delete them).

Then every output is written by one of two writers, the only places that write results:

* :func:`write_or_fallback` (files; :func:`write_text` for text) -- ``write(tmp)`` fills a
  temporary sibling of the file, which is flushed to disk (``fsync``) and renamed onto it: the
  file is either the old one or the new one, never a truncated mix (a full disk or a kill
  mid-write leaves the old file as it was);
* :func:`write_dir` / :func:`staged_dir` (folders) -- the run writes into a hidden temporary
  sibling folder, whose files are flushed and which then replaces the folder whole (one
  atomic exchange where the system has it): no mix of two runs and no half-written folder.

When writing still fails (disk full, permissions changed meanwhile), :func:`write_or_fallback`
and :func:`write_dir` write the finished result to a temporary file or folder instead
(``$TMPDIR``) and the error names it, so nothing computed is thrown away (docs/errors.md,
"Rules every command follows").  Outputs get the modes the umask gives (0644 / 0755 under
022), like any file the user creates.  Staging folders left by a killed run are removed by the
next run into the same place.

Refusals are :class:`elastimap.errors.UserError` naming the parameter; nothing is created
on disk by a check.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import UserError

__all__ = [
    "check_out_file",
    "check_out_dir",
    "check_inputs_kept",
    "figure_suffixes",
    "staged_dir",
    "write_dir",
    "publish_dir",
    "write_or_fallback",
    "write_text",
    "is_empty_dir",
    "umask",
]


def umask() -> int:
    """The process umask (read without changing it where /proc allows)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    m = os.umask(0o022)
    os.umask(m)
    return m


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


class _WriteFailed(UserError):
    """Writing a run's results failed with an OS error (disk full); nothing was changed."""


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def check_out_file(
    path: str | os.PathLike,
    param: str,
    *,
    create_parents: bool = False,
    suffixes: tuple[str, ...] | None = None,
    inputs: dict[str, str | os.PathLike | None] | None = None,
) -> Path:
    """A file about to be written: not a folder, in an existing folder we may write in
    (with ``create_parents``: in a folder the writer may create), with one of ``suffixes``
    (e.g. :func:`figure_suffixes`) when given, and none of the command's ``inputs``
    (``{"--flag": path}``) nor inside an input folder (:func:`check_inputs_kept`).

    An existing file is allowed (the caller decides whether replacing it is right); a symbolic
    link is written through to its target, so one that leads nowhere (a loop, a missing
    target) is refused here, before the work."""
    p = Path(path)
    if not str(path):
        raise UserError(param, "must name a file (got an empty string)")
    if suffixes and p.suffix.lower() not in suffixes:
        raise UserError(param, f"{p}: the file name must end in {', '.join(suffixes)}")
    check_inputs_kept(p, param, **(inputs or {}))
    try:
        is_dir = p.is_dir()
    except OSError as exc:  # a name too long, a loop in a folder above it
        raise UserError(param, f"cannot write {p} ({_reason(exc)})") from None
    if is_dir:
        raise UserError(param, f"{p} is a folder; give a file name")
    if os.path.islink(p) and not os.path.exists(p):
        raise UserError(param, f"{p} is a symbolic link that leads nowhere (a loop or a missing target)")
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
    marker: str | None = None,
) -> Path:
    """A folder about to be filled.

    Refused: a file at ``path``; a folder we cannot write in (or create); a folder that
    already holds files, unless ``overwrite`` (the caller replaces it whole; with ``marker``,
    only a folder holding that file, the mark of the command's own earlier result) or
    ``allow_existing`` (the caller adds to it, e.g. a resumable sweep)."""
    p = Path(path)
    if os.path.lexists(p) and not p.is_dir():
        raise UserError(param, f"{p} is a file, not a folder")
    if p.is_dir():
        if not os.access(p, os.W_OK | os.X_OK):
            raise UserError(param, f"cannot write in {p}: no write permission")
        if not (overwrite or allow_existing or is_empty_dir(p)):
            raise UserError(param, f"{p} already holds files; give {hint} to replace it, or choose another folder")
        if overwrite and marker and not is_empty_dir(p) and not (p / marker).is_file():
            raise UserError(
                param, f"{p} holds files but no {marker}: {hint} replaces only an earlier result; choose another folder"
            )
        if overwrite and not os.access(p.parent if str(p.parent) else Path("."), os.W_OK | os.X_OK):
            raise UserError(param, f"cannot replace {p}: no write permission in {p.parent}")
    else:
        _check_creatable(p, param)
    return p


def _within(p: Path, folder: Path) -> bool:
    real, root = os.path.realpath(p), os.path.realpath(folder)
    return real == root or real.startswith(root.rstrip(os.sep) + os.sep)


def check_inputs_kept(out: str | os.PathLike, param: str, **inputs: str | os.PathLike | None) -> None:
    """Refuse an output (file or folder) that is, holds or lies inside one of the command's inputs
    (``flag=path``; ``data``, ``"--data"`` or an argument ``PATH``): replacing ``out`` whole (``--overwrite``, a staged
    run) would delete the input data, and writing into an input folder would mix the results
    with the data."""
    for flag, path in inputs.items():
        if path is None or not str(path) or not os.path.lexists(path):
            continue
        name = flag if flag.startswith("-") or flag.isupper() else "--" + flag.replace("_", "-")
        if _within(Path(path), Path(out)):
            raise UserError(
                param,
                f"{out} is or holds the input {name} {path}; writing the results there would replace it "
                "(choose another name)",
            )
        if os.path.isdir(path) and _within(Path(out), Path(path)):
            raise UserError(
                param, f"{out} lies inside the input {name} {path}; write the results outside the input folder"
            )


def figure_suffixes() -> tuple[str, ...]:
    """The file-name endings matplotlib can save a figure as (``.png``, ``.pdf``, ``.svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted("." + k for k in FigureCanvasBase.get_supported_filetypes()))


# ----------------------------------------------------------------------------- files
def _fsync_file(path: str | os.PathLike) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: str | os.PathLike) -> None:
    """Make a rename in ``path`` durable (a no-op where folders cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _target(p: Path) -> Path:
    """Where writing ``p`` lands: through a symbolic link to its target."""
    return Path(os.path.realpath(p)) if os.path.islink(p) else p


def _write_atomic(p: Path, write: Callable[[str], object]) -> None:
    """``write`` a temporary sibling of ``p`` (same suffix: numpy and matplotlib read it), flush it,
    give it the umask's mode and rename it onto ``p``; on any error the sibling is removed."""
    tmp = p.with_name(f".{p.stem}.{uuid.uuid4().hex[:8]}.partial{p.suffix}")
    try:
        write(str(tmp))
        _fsync_file(tmp)
        os.chmod(tmp, 0o666 & ~umask())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _fsync_dir(p.parent if str(p.parent) else ".")


def write_or_fallback(
    write: Callable[[str], object], path: str | os.PathLike, param: str, *, fallback: bool = True
) -> Path:
    """Write one output file whole: ``write(name)`` fills a temporary sibling of ``path`` that
    replaces it only once complete and flushed (see the module docstring).

    If that fails with an OS error (disk full, no permission), ``path`` is left as it was, the
    result is written to a temporary file in ``$TMPDIR`` instead (not with ``fallback=False``:
    one of many files, such as a frame), and :class:`UserError` names both, so a finished result
    is never thrown away.  Returns the path written."""
    p = Path(path)
    try:
        _write_atomic(_target(p), write)
        return p
    except OSError as exc:
        reason = _reason(exc)
    if not fallback:
        raise UserError(param, f"cannot write {p} ({reason}); {p} is unchanged")
    fb = _fallback_file(p)
    try:
        _write_atomic(fb, write)
    except OSError:
        try:
            os.unlink(fb)
        except OSError:
            pass
        raise UserError(
            param, f"cannot write {p} ({reason}), nor a fallback copy in {tempfile.gettempdir()}; {p} is unchanged"
        ) from None
    raise UserError(param, f"cannot write {p} ({reason}); the result was saved to {fb} instead") from None


def _fallback_file(p: Path) -> Path:
    fd, fb = tempfile.mkstemp(prefix=f"elastimap-{p.stem}-", suffix=p.suffix)
    os.close(fd)
    return Path(fb)


def write_text(path: str | os.PathLike, text: str, param: str) -> Path:
    """:func:`write_or_fallback` of a text (UTF-8)."""

    def _write(name: str) -> None:
        with open(name, "w", encoding="utf-8") as fh:
            fh.write(text)

    return write_or_fallback(_write, path, param)


# ----------------------------------------------------------------------------- folders
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the
    system or the file system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    rc = fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def publish_dir(tmp: Path, final: Path, param: str = "out") -> Path:
    """Move a finished temporary folder to ``final``, replacing what was there as a whole.

    Where the system allows, the two folders are exchanged in one step, so ``final`` is at
    every moment either the old folder or the new one; elsewhere the old folder is first moved
    aside (and put back if the move of the new one fails)."""
    old = None
    try:
        if os.path.isdir(final) and not os.path.islink(final) and _exchange(tmp, final):
            old = tmp  # it holds the previous folder now
        else:
            if os.path.lexists(final):
                old = final.with_name(f".{final.name}.old-{uuid.uuid4().hex[:8]}")
                os.replace(final, old)
            os.replace(tmp, final)
    except OSError as exc:
        if old is not None and old != tmp and not os.path.lexists(final):
            try:
                os.replace(old, final)
                old = None
            except OSError:
                pass
        raise UserError(
            param, f"could not move the finished result to {final} ({_reason(exc)}); it is kept in {tmp}"
        ) from None
    _fsync_dir(final.parent if str(final.parent) else ".")
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return final


def _fsync_tree(root: Path) -> None:
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            fp = os.path.join(dirpath, f)
            if not os.path.islink(fp):
                _fsync_file(fp)
        _fsync_dir(dirpath)


def _hold(folder: Path) -> int:
    """An exclusive lock on ``folder`` held by this process while it fills it (released when the
    process ends, however it ends): how the next run tells a stale staging folder from a live one."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


def _remove_stale_stages(final: Path) -> list[Path]:
    """Remove staging folders of ``final`` left by runs that were killed (nobody holds their lock)."""
    parent = final.parent if str(final.parent) else Path(".")
    removed = []
    for cand in parent.glob(f".{final.name}.*.partial"):
        if not cand.is_dir() or cand.is_symlink():
            continue
        try:
            fd = os.open(cand, os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue  # a run that is alive
        finally:
            os.close(fd)
        shutil.rmtree(cand, ignore_errors=True)
        removed.append(cand)
    return removed


def _new_stage(parent: Path, name: str) -> tuple[Path, int]:
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", suffix=".partial", dir=parent))
    os.chmod(tmp, 0o777 & ~umask())
    return tmp, _hold(tmp)


@contextmanager
def staged_dir(final: str | os.PathLike, param: str = "out", *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary sibling of ``final`` to write one run's results into.

    On success its files are flushed and it replaces ``final`` whole (:func:`publish_dir`; an
    earlier folder is removed only after the new one is in place); on any error it is removed
    and ``final`` is untouched; an OS error while writing (disk full) becomes a
    :class:`UserError` saying so.  ``final`` is checked first (:func:`check_out_dir`): an existing
    non-empty folder needs ``overwrite``.  Use :func:`write_dir` where the results can be written
    again elsewhere: it keeps them when writing fails."""
    final = Path(final)
    check_out_dir(final, param, overwrite=overwrite)
    parent = final.parent if str(final.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_stages(final)
    tmp, fd = _new_stage(parent, final.name)
    try:
        try:
            yield tmp
            _fsync_tree(tmp)
        except OSError as exc:
            raise _WriteFailed(
                param, f"cannot write the results for {final} ({_reason(exc)}); {final} is unchanged"
            ) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        os.close(fd)
        raise
    try:
        publish_dir(tmp, final, param)
    finally:
        os.close(fd)


def write_dir(
    final: str | os.PathLike, write: Callable[[Path], object], param: str = "out", *, overwrite: bool = False
) -> Path:
    """Write one run's results as a folder, whole: ``write(folder)`` fills a staging sibling of
    ``final`` that replaces it once complete (:func:`staged_dir`).

    If writing fails with an OS error (disk full), ``final`` is left as it was, ``write`` runs
    again into a new folder in ``$TMPDIR`` and :class:`UserError` names it, so the finished result
    is kept.  Returns ``final``."""
    final = Path(final)
    try:
        with staged_dir(final, param, overwrite=overwrite) as tmp:
            write(tmp)
        return final
    except _WriteFailed as exc:
        reason = exc.message
    fb = Path(tempfile.mkdtemp(prefix=f"elastimap-{final.name}-"))
    os.chmod(fb, 0o777 & ~umask())
    try:
        write(fb)
        _fsync_tree(fb)
    except OSError:
        shutil.rmtree(fb, ignore_errors=True)
        raise UserError(param, f"{reason}, nor a fallback copy in {tempfile.gettempdir()}") from None
    raise UserError(param, f"{reason}; the result was saved to {fb} instead")

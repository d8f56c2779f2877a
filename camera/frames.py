"""Reading and writing camera frames (8/12/16-bit PNG and TIFF, multi-page TIFF stacks).

Reading (:mod:`elastimap.camera.framefiles`) is defensive: a missing, empty, corrupt,
wrong-size file, or frames of mixed sizes or bit depths, raise :class:`UserError` naming the
file; colour frames are converted to grey with a warning; a frame with clipped (saturated)
pixels in the footprint window, a blank frame or dropped pages get a :class:`CameraWarning`
naming the file.

Synthetic frames are written with ``synthetic`` in the file name and the
metadata (PNG text chunk ``synthetic``/``description``, TIFF ImageDescription).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from elastimap.errors import UserError

from .framefiles import MAX_PIXELS, SATURATION_WARN_FRACTION, CameraWarning, read_frames

__all__ = [
    "CameraWarning",
    "MAX_PIXELS",
    "SATURATION_WARN_FRACTION",
    "read_frame",
    "read_stack",
    "write_frames",
    "read_metadata",
    "expand",
]

FORMATS = ("png", "tiff")


def write_frames(
    frames: np.ndarray,
    directory: str | os.PathLike,
    prefix: str,
    fmt: str = "png",
    metadata: dict | None = None,
    synthetic: bool = True,
) -> list[str]:
    """Write ``frames`` (n, rows, cols; uint8 or uint16) as ``<prefix>_fNNN.<ext>``; return the paths.

    ``synthetic=True`` prefixes the file names with ``synthetic_`` (unless the
    prefix already says so) and records ``synthetic: true`` in the metadata.
    """
    from PIL import Image, PngImagePlugin

    if fmt not in FORMATS:
        raise UserError("format", f"must be one of {', '.join(FORMATS)} (got {fmt!r})")
    frames = np.asarray(frames)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.dtype not in (np.uint8, np.uint16):
        raise UserError("frames", f"must be uint8 or uint16 (got {frames.dtype})")
    if synthetic and "synthetic" not in prefix:
        prefix = f"synthetic_{prefix}"
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    meta = dict(metadata or {})
    meta["synthetic"] = bool(synthetic)
    meta["bits"] = 8 if frames.dtype == np.uint8 else 16
    text = json.dumps(meta, sort_keys=True, default=str)
    ext = "png" if fmt == "png" else "tif"
    from elastimap.outputs import write_or_fallback

    paths = []
    for i, f in enumerate(frames):
        p = d / f"{prefix}_f{i:03d}.{ext}"
        im = Image.fromarray(np.ascontiguousarray(f))
        if fmt == "png":
            info = PngImagePlugin.PngInfo()
            info.add_text("synthetic", "true" if synthetic else "false")
            info.add_text("description", text)
            save = lambda name, im=im, info=info: im.save(name, format="PNG", pnginfo=info)  # noqa: E731
        else:
            save = lambda name, im=im: im.save(name, format="TIFF", tiffinfo={270: text})  # noqa: E731
        write_or_fallback(save, p, "out", fallback=False)  # each frame whole, never a truncated file
        paths.append(str(p))
    return paths


def read_metadata(path: str | os.PathLike) -> dict:
    """The JSON metadata written by :func:`write_frames` ({} if none)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            text = None
            if hasattr(im, "text"):
                text = im.text.get("description")
            if text is None and hasattr(im, "tag_v2"):
                text = im.tag_v2.get(270)
        return json.loads(text) if text else {}
    except Exception:
        return {}


def read_frame(
    path: str | os.PathLike,
    shape: tuple[int, int] | None = None,
    window: tuple[int, int, int] | None = None,
    param: str = "image",
) -> tuple[np.ndarray, int]:
    """Read the first frame of a file; return (float array in DN, full-scale DN).

    ``shape`` (rows, cols), when given, must match; it is checked from the file's header, before
    the pixels are decoded, and no frame may have more than :data:`MAX_PIXELS` pixels (a damaged or
    hostile header claiming 100000x100000 px is refused, not decoded).  ``window`` (row0, col0, n)
    restricts the saturation check to the footprint.  Problems are :class:`UserError` naming
    ``param`` and the file.  A file holding more frames (a TIFF stack) is warned about:
    :func:`read_stack` reads them all.
    """
    frames, full = read_frames([str(path)], shape, window, param=param)
    if len(frames) > 1:
        warnings.warn(
            f"{path}: {len(frames) - 1} of {len(frames)} frames dropped (only the first read; read_stack reads all)",
            CameraWarning,
            stacklevel=2,
        )
    return frames[0], full


def read_stack(
    paths: list[str],
    shape: tuple[int, int] | None = None,
    window: tuple[int, int, int] | None = None,
    param: str = "images",
    bits: int | None = None,
) -> tuple[np.ndarray, int]:
    """Every frame of every file (multi-page TIFF stacks included), of one size and bit depth;
    return (n, rows, cols) float DN and full scale (:func:`elastimap.camera.framefiles.read_frames`)."""
    return read_frames(paths, shape, window, bits, param)


def _inside(path: str, folder: str) -> bool:
    real, root = os.path.realpath(path), os.path.realpath(folder)
    return real == root or real.startswith(root.rstrip(os.sep) + os.sep)


def expand(
    spec: str | list[str],
    base: str | os.PathLike | None = None,
    *,
    param: str = "images",
    allow_outside: bool = False,
    switch: str = "--allow-outside",
) -> list[str]:
    """File list from a list, a ';'-separated string or glob patterns (relative to ``base``).

    With ``base`` (the folder of the table that holds the names) every name and every file a
    pattern matches must lie inside ``base`` -- no absolute paths, no ``..`` and no symbolic link
    out of it -- unless ``allow_outside`` (the command's ``switch``, named in the refusal): a
    table handed over with a dataset cannot make a command read, or list, files elsewhere.
    Problems are :class:`UserError` naming ``param``."""
    import glob

    items = spec if isinstance(spec, (list, tuple)) else [s for s in str(spec).split(";")]
    confine = base is not None and not allow_outside
    out: list[str] = []
    for s in items:
        s = str(s).strip()
        if not s:
            continue
        climbs = ".." in Path(s).parts
        if base is not None and not os.path.isabs(s):
            s = os.path.join(str(base), s)
        outside = f"{s}: outside the folder {base} (a table's files are read only inside its folder; give {switch} to allow it)"
        stem = s.split("*")[0].split("?")[0].split("[")[0]  # the part before any wildcard
        if confine and (climbs or not _inside(os.path.dirname(stem) or ".", str(base))):
            raise UserError(param, outside)
        hits = sorted(glob.glob(s)) if any(ch in s for ch in "*?[") else [s]
        if not hits:
            raise UserError(param, f"{s}: pattern matches no files")
        if confine and not all(_inside(h, str(base)) for h in hits):
            raise UserError(param, outside)
        out.extend(hits)
    return out

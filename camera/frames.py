"""Reading and writing camera frames (8/16-bit PNG and TIFF).

Reading is defensive: a missing, empty, corrupt, wrong-size or colour file
raises :class:`UserError` naming the file (or, for colour, warns and converts);
a frame with clipped (saturated) pixels in the footprint window, or a blank
frame, gets a :class:`CameraWarning` naming the file.

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

FORMATS = ("png", "tiff")
SATURATION_WARN_FRACTION = 1e-3  # warn when more than 0.1 % of the window pixels are clipped
MAX_PIXELS = 1 << 26  # 67 Mpx: far above any sensor frame, far below what would exhaust memory


class CameraWarning(UserWarning):
    """A frame is usable but suspicious (saturated, blank, colour)."""


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
    """Read one frame; return (float array in DN, full-scale DN).

    ``shape`` (rows, cols), when given, must match; it is checked from the file's header, before
    the pixels are decoded, and no frame may have more than :data:`MAX_PIXELS` pixels (a damaged or
    hostile header claiming 100000x100000 px is refused, not decoded).  ``window`` (row0, col0, n)
    restricts the saturation check to the footprint.  Problems are :class:`UserError` naming
    ``param`` and the file.
    """
    from PIL import Image, UnidentifiedImageError

    p = str(path)
    if not os.path.exists(p):
        raise UserError(param, f"{p}: no such file")
    if os.path.isdir(p):
        raise UserError(param, f"{p}: is a directory, not an image")
    if os.path.getsize(p) == 0:
        raise UserError(param, f"{p}: empty file (0 bytes)")
    try:
        with Image.open(p) as im:
            cols, rows = im.size
            if shape is not None and (rows, cols) != tuple(shape):
                raise UserError(param, f"{p}: wrong size {cols}x{rows} (cols x rows); expected {shape[1]}x{shape[0]}")
            if rows * cols > MAX_PIXELS:
                raise UserError(param, f"{p}: {cols}x{rows} pixels is more than the {MAX_PIXELS} a frame may have")
            im.load()
            mode = im.mode
            if mode in ("RGB", "RGBA", "P", "LA", "CMYK", "YCbCr"):
                warnings.warn(f"{p}: colour image (mode {mode}) converted to grey", CameraWarning, stacklevel=2)
                im = im.convert("L")
                mode = "L"
            arr = np.array(im)
    except UserError:
        raise  # the size checks above (a UserError is a ValueError: not "corrupt")
    except UnidentifiedImageError:
        raise UserError(param, f"{p}: not a readable PNG/TIFF image (corrupt or unknown format)") from None
    except Image.DecompressionBombError as exc:
        raise UserError(param, f"{p}: refused, too many pixels ({exc})") from None
    except (OSError, SyntaxError, ValueError, MemoryError) as exc:
        raise UserError(param, f"{p}: corrupt or truncated image ({exc})") from None
    if arr.ndim != 2:
        raise UserError(param, f"{p}: expected a single-channel image (got array shape {arr.shape})")
    if arr.size == 0:
        raise UserError(param, f"{p}: image has no pixels")
    if arr.dtype == np.uint8 or mode in ("L", "1"):
        full = 255
    elif arr.dtype in (np.uint16, np.int32, np.int16, np.uint32) or mode.startswith("I"):
        full = 65535
    elif arr.dtype.kind == "f":
        raise UserError(param, f"{p}: floating-point images are not supported (use 8- or 16-bit integers)")
    else:
        raise UserError(param, f"{p}: unsupported pixel type {arr.dtype} (mode {mode})")
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise UserError(
            param, f"{p}: wrong size {arr.shape[1]}x{arr.shape[0]} (cols x rows); expected {shape[1]}x{shape[0]}"
        )
    a = arr.astype(float)
    sub = a if window is None else a[window[0] : window[0] + window[2], window[1] : window[1] + window[2]]
    if sub.size:
        sat = float(np.count_nonzero(sub >= full)) / sub.size
        if sat > SATURATION_WARN_FRACTION:
            warnings.warn(
                f"{p}: {100 * sat:.2g} % of the footprint pixels are saturated "
                f"(at {full}); features will be biased low",
                CameraWarning,
                stacklevel=2,
            )
        if sub.max() == sub.min():
            warnings.warn(f"{p}: blank frame (all pixels {sub.max():g})", CameraWarning, stacklevel=2)
    return a, full


def read_stack(
    paths: list[str],
    shape: tuple[int, int] | None = None,
    window: tuple[int, int, int] | None = None,
    param: str = "images",
) -> tuple[np.ndarray, int]:
    """Read several frames of one size and bit depth; return (n, rows, cols) float DN and full scale."""
    if not paths:
        raise UserError(param, "no image files given")
    frames, full = [], None
    for p in paths:
        a, fs = read_frame(p, shape, window, param)
        if shape is None:
            shape = a.shape
        if full is None:
            full = fs
        elif fs != full:
            raise UserError(param, f"{p}: bit depth differs from {paths[0]} (full scale {fs} vs {full})")
        frames.append(a)
    return np.stack(frames), int(full)


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

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
    paths = []
    for i, f in enumerate(frames):
        p = d / f"{prefix}_f{i:03d}.{ext}"
        im = Image.fromarray(np.ascontiguousarray(f))
        if fmt == "png":
            info = PngImagePlugin.PngInfo()
            info.add_text("synthetic", "true" if synthetic else "false")
            info.add_text("description", text)
            im.save(p, pnginfo=info)
        else:
            im.save(p, tiffinfo={270: text})
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
    path: str | os.PathLike, shape: tuple[int, int] | None = None, window: tuple[int, int, int] | None = None
) -> tuple[np.ndarray, int]:
    """Read one frame; return (float array in DN, full-scale DN).

    ``shape`` (rows, cols), when given, must match.  ``window`` (row0, col0, n)
    restricts the saturation check to the footprint.
    """
    from PIL import Image, UnidentifiedImageError

    p = str(path)
    if not os.path.exists(p):
        raise UserError("image", f"{p}: no such file")
    if os.path.isdir(p):
        raise UserError("image", f"{p}: is a directory, not an image")
    if os.path.getsize(p) == 0:
        raise UserError("image", f"{p}: empty file (0 bytes)")
    try:
        with Image.open(p) as im:
            im.load()
            mode = im.mode
            if mode in ("RGB", "RGBA", "P", "LA", "CMYK", "YCbCr"):
                warnings.warn(f"{p}: colour image (mode {mode}) converted to grey", CameraWarning, stacklevel=2)
                im = im.convert("L")
                mode = "L"
            arr = np.array(im)
    except UnidentifiedImageError:
        raise UserError("image", f"{p}: not a readable PNG/TIFF image (corrupt or unknown format)") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise UserError("image", f"{p}: corrupt or truncated image ({exc})") from None
    if arr.ndim != 2:
        raise UserError("image", f"{p}: expected a single-channel image (got array shape {arr.shape})")
    if arr.size == 0:
        raise UserError("image", f"{p}: image has no pixels")
    if arr.dtype == np.uint8 or mode in ("L", "1"):
        full = 255
    elif arr.dtype in (np.uint16, np.int32, np.int16, np.uint32) or mode.startswith("I"):
        full = 65535
    elif arr.dtype.kind == "f":
        raise UserError("image", f"{p}: floating-point images are not supported (use 8- or 16-bit integers)")
    else:
        raise UserError("image", f"{p}: unsupported pixel type {arr.dtype} (mode {mode})")
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise UserError(
            "image", f"{p}: wrong size {arr.shape[1]}x{arr.shape[0]} (cols x rows); expected {shape[1]}x{shape[0]}"
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
    paths: list[str], shape: tuple[int, int] | None = None, window: tuple[int, int, int] | None = None
) -> tuple[np.ndarray, int]:
    """Read several frames of one size and bit depth; return (n, rows, cols) float DN and full scale."""
    if not paths:
        raise UserError("images", "no image files given")
    frames, full = [], None
    for p in paths:
        a, fs = read_frame(p, shape, window)
        if shape is None:
            shape = a.shape
        if full is None:
            full = fs
        elif fs != full:
            raise UserError("image", f"{p}: bit depth differs from {paths[0]} (full scale {fs} vs {full})")
        frames.append(a)
    return np.stack(frames), int(full)


def expand(spec: str | list[str], base: str | os.PathLike | None = None) -> list[str]:
    """File list from a list, a ';'-separated string or glob patterns (relative to ``base``)."""
    import glob

    items = spec if isinstance(spec, (list, tuple)) else [s for s in str(spec).split(";")]
    out: list[str] = []
    for s in items:
        s = str(s).strip()
        if not s:
            continue
        if base is not None and not os.path.isabs(s):
            s = os.path.join(str(base), s)
        hits = sorted(glob.glob(s)) if any(ch in s for ch in "*?[") else [s]
        if not hits:
            raise UserError("images", f"{s}: pattern matches no files")
        out.extend(hits)
    return out

"""Frame files as labs save them: multi-page TIFF stacks, 8/12/16-bit PNG and TIFF.

One file may hold one frame (PNG, single-page TIFF) or many (a multi-page TIFF stack, as lab
cameras and ImageJ save them); :func:`read_frames` reads every frame of every file given, in
order, as one stack ``(n, rows, cols)`` of DN with one full scale.

Bit depth (the full scale is ``2^bits - 1``): what the file says its significant bits are (a PNG
``sBIT`` chunk, a packed TIFF's ``BitsPerSample``), else its container (8 or 16 bits).  12-bit cameras
usually store their frames in 16-bit containers without saying so: pass ``bits=12`` (the camera's
``bits`` in the sensor description) and the frames are read against 4095, a value above it
refused.  A file recording its bits is read at them.

What is refused, each as one :class:`UserError` naming the file: a missing, empty, corrupt or
floating-point file; frames of different sizes or bit depths (within a stack or across files);
a size other than ``shape``.  What is warned about (:class:`CameraWarning`, naming the file):
colour frames (converted to grey), pages dropped (the reduced-resolution previews/thumbnails
some TIFF writers add), saturated or blank frames in the footprint ``window``.

TIFF is read with tifffile, PNG with Pillow; a packed 12-bit TIFF needs the optional imagecodecs
(``pip install 'elastimap[frames]'``, in the ``dev`` extra), else it is refused with one line saying so.
"""

from __future__ import annotations

import os
import struct
import warnings

import numpy as np

from elastimap.errors import UserError

BITS = (8, 12, 16)
SATURATION_WARN_FRACTION = 1e-3  # warn when more than 0.1 % of the window pixels are clipped
MAX_PIXELS = 1 << 26  # 67 Mpx: far above any sensor frame, far below what would exhaust memory
#: ITU-R 601-2 luma, as Pillow's convert("L")
_LUMA = np.array([0.299, 0.587, 0.114])


class CameraWarning(UserWarning):
    """A frame is usable but suspicious (saturated, blank, colour, pages dropped)."""


def _check_header(p: str, param: str, rows: int, cols: int, shape) -> None:
    """A frame's size from the file's header, before its pixels are decoded: ``shape`` (rows, cols)
    when given, and at most :data:`MAX_PIXELS` pixels (a damaged or hostile header is refused)."""
    if shape is not None and (rows, cols) != tuple(shape):
        raise UserError(param, f"{p}: wrong size {cols}x{rows} (cols x rows); expected {shape[1]}x{shape[0]}")
    if rows * cols > MAX_PIXELS:
        raise UserError(param, f"{p}: {cols}x{rows} pixels is more than the {MAX_PIXELS} a frame may have")


def _check_file(p: str, param: str) -> None:
    if not os.path.exists(p):
        raise UserError(param, f"{p}: no such file")
    if os.path.isdir(p):
        raise UserError(param, f"{p}: is a directory, not an image")
    if os.path.getsize(p) == 0:
        raise UserError(param, f"{p}: empty file (0 bytes)")


def _is_tiff(p: str) -> bool:
    with open(p, "rb") as fh:
        head = fh.read(4)
    return head in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def _png_significant_bits(p: str) -> int | None:
    """The grey significant bits of a PNG's ``sBIT`` chunk (None when it has none)."""
    with open(p, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return None
        while True:
            head = fh.read(8)
            if len(head) < 8:
                return None
            length, kind = struct.unpack(">I4s", head)
            if kind == b"sBIT":
                data = fh.read(length)
                return max(data) if data else None
            if kind in (b"IDAT", b"IEND"):
                return None
            fh.seek(length + 4, os.SEEK_CUR)  # data and CRC


def _grey(a: np.ndarray, p: str, what: str) -> np.ndarray:
    warnings.warn(f"{p}: colour image ({what}) converted to grey", CameraWarning, stacklevel=4)
    return np.rint(a[..., :3].astype(float) @ _LUMA).astype(a.dtype)


def _read_tiff(p: str, param: str, shape=None) -> tuple[np.ndarray, int | None]:
    import logging

    import tifffile

    # tifffile logs what it cannot parse; the one error line below names the file and the reason
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    try:
        with tifffile.TiffFile(p) as tif:
            pages, dropped, bits = [], 0, set()
            for page in tif.pages:
                if getattr(page, "subfiletype", 0) & 1:  # a reduced-resolution preview, not a frame
                    dropped += 1
                    continue
                if len(page.shape) >= 2:
                    _check_header(p, param, int(page.imagelength), int(page.imagewidth), shape if not pages else None)
                a = page.asarray()
                if page.samplesperpixel > 1:
                    a = _grey(a if a.shape[-1] == page.samplesperpixel else np.moveaxis(a, 0, -1), p, "RGB")
                pages.append((a, page.index))
                bits.add(int(page.bitspersample))
    except UserError:
        raise
    except NotImplementedError as exc:  # packed 12-bit or exotic compression: tifffile needs imagecodecs
        hint = (
            "; install the optional imagecodecs (pip install 'elastimap[frames]')" if "imagecodecs" in str(exc) else ""
        )
        raise UserError(param, f"{p}: this TIFF's encoding cannot be read here ({exc}){hint}") from None
    except (tifffile.TiffFileError, ValueError, OSError, KeyError, IndexError, struct.error) as exc:
        raise UserError(param, f"{p}: not a readable TIFF (corrupt or truncated: {exc})") from None
    if dropped:
        warnings.warn(
            f"{p}: {dropped} reduced-resolution page(s) (previews) dropped; {len(pages)} frame(s) read",
            CameraWarning,
            stacklevel=3,
        )
    if not pages:
        raise UserError(param, f"{p}: not a readable TIFF (no full-resolution frame found)")
    first, _ = pages[0]
    for a, i in pages[1:]:
        if a.shape != first.shape:
            raise UserError(
                param, f"{p}: page {i + 1} is {_size(a.shape)}, page 1 {_size(first.shape)}: mixed frame sizes"
            )
        if a.dtype != first.dtype:
            raise UserError(param, f"{p}: page {i + 1} is {a.dtype}, page 1 {first.dtype}: mixed bit depths")
    if len(bits) > 1:
        raise UserError(param, f"{p}: pages of {sorted(bits)} bits: mixed bit depths")
    stated = bits.pop()  # BitsPerSample says more than the container only for packed data (12 bits)
    return np.stack([a for a, _ in pages]), (stated if stated != 8 * first.dtype.itemsize else None)


def _read_png(p: str, param: str, shape=None) -> tuple[np.ndarray, int | None]:
    from PIL import Image, ImageSequence, UnidentifiedImageError

    try:
        with Image.open(p) as im:
            cols, rows = im.size
            _check_header(p, param, rows, cols, shape)
            frames = []
            for frame in ImageSequence.Iterator(im):
                mode = frame.mode
                if mode in ("RGB", "RGBA", "P", "LA", "CMYK", "YCbCr"):
                    warnings.warn(f"{p}: colour image (mode {mode}) converted to grey", CameraWarning, stacklevel=3)
                    frame = frame.convert("L")
                elif mode == "1":
                    frame = frame.convert("L")
                frames.append(np.array(frame))
    except UserError:
        raise  # the size checks above (a UserError is a ValueError: not "corrupt")
    except UnidentifiedImageError:
        raise UserError(param, f"{p}: not a readable PNG/TIFF image (corrupt or unknown format)") from None
    except Image.DecompressionBombError as exc:
        raise UserError(param, f"{p}: refused, too many pixels ({exc})") from None
    except (OSError, SyntaxError, ValueError, EOFError, MemoryError) as exc:
        raise UserError(param, f"{p}: corrupt or truncated image ({exc})") from None
    shapes = {a.shape for a in frames}
    if len(shapes) > 1:
        raise UserError(param, f"{p}: frames of sizes {sorted(_size(s) for s in shapes)}: mixed frame sizes")
    return np.stack(frames), _png_significant_bits(p)


def _size(shape) -> str:
    return f"{shape[1]}x{shape[0]} (cols x rows)" if len(shape) >= 2 else str(shape)


def read_file(
    path: str | os.PathLike, bits: int | None = None, param: str = "image", shape: tuple[int, int] | None = None
) -> tuple[np.ndarray, int]:
    """Every frame of one file: ``(frames (n, rows, cols) as float DN, full scale)``.

    ``bits`` (8, 12 or 16): the camera's bit depth, which reads a container of more bits that
    does not record its significant bits (12-bit data in 16-bit files) against ``2^bits - 1``;
    a value above it is refused.  A file of fewer bits than ``bits`` is read at its own depth
    (callers compare the full scale with the camera's where it matters).
    """
    p = str(path)
    _check_file(p, param)
    if bits is not None and bits not in BITS:
        raise UserError("bits", f"must be one of {', '.join(map(str, BITS))} (got {bits})")
    arr, stated = _read_tiff(p, param, shape) if _is_tiff(p) else _read_png(p, param, shape)
    if arr.dtype.kind == "f":
        raise UserError(param, f"{p}: floating-point images are not supported (use 8-, 12- or 16-bit integers)")
    if arr.dtype.kind not in "ui" or arr.ndim != 3:
        raise UserError(param, f"{p}: unsupported pixel type {arr.dtype} (shape {arr.shape})")
    if arr.size == 0:
        raise UserError(param, f"{p}: image has no pixels")
    container = 8 if arr.dtype.itemsize == 1 else 16
    if arr.dtype.itemsize > 2 and arr.max(initial=0) > 65535:  # Pillow reads 16-bit PNG as int32
        raise UserError(param, f"{p}: values above 65535: at most 16 bits per pixel are supported")
    depth = stated if stated in BITS and stated <= container else container
    if bits is not None and stated is None and bits < container:
        depth = bits  # e.g. a 12-bit camera's frames in 16-bit containers
    full = 2**depth - 1
    if arr.min(initial=0) < 0 or arr.max(initial=0) > full:
        raise UserError(
            param, f"{p}: values up to {int(arr.max())} do not fit {depth} bits (full scale {full}): wrong --bits?"
        )
    return arr.astype(float), full


def read_frames(
    paths: list[str],
    shape: tuple[int, int] | None = None,
    window: tuple[int, int, int] | None = None,
    bits: int | None = None,
    param: str = "images",
) -> tuple[np.ndarray, int]:
    """Every frame of every file, in order: ``(frames (n, rows, cols) float DN, full scale)``.

    All frames must have one size (``shape`` (rows, cols) when given) and one bit depth;
    ``window`` (row0, col0, n) limits the saturation and blank checks to the footprint.
    """
    if not paths:
        raise UserError(param, "no image files given")
    stacks, full = [], None
    for p in paths:
        a, fs = read_file(p, bits, param, shape)
        if shape is None:
            shape = a.shape[1:]
        if tuple(a.shape[1:]) != tuple(shape):
            raise UserError(param, f"{p}: wrong size {_size(a.shape[1:])}; expected {_size(shape)}")
        if full is None:
            full = fs
        elif fs != full:
            raise UserError(param, f"{p}: bit depth differs from {paths[0]} (full scale {fs} vs {full})")
        check_exposure(a, full, window, p)
        stacks.append(a)
    return np.concatenate(stacks), int(full)


def check_exposure(frames: np.ndarray, full: int, window: tuple[int, int, int] | None, p: str) -> None:
    """Warn (:class:`CameraWarning`) about frames of one file with clipped pixels in the footprint
    ``window`` (more than 0.1 %) or with no contrast at all."""
    sub = frames if window is None else frames[:, window[0] : window[0] + window[2], window[1] : window[1] + window[2]]
    if not sub.size:
        return
    n = len(sub)
    sat = np.count_nonzero(sub >= full, axis=(1, 2)) / sub[0].size
    bad = sat > SATURATION_WARN_FRACTION
    if bad.any():
        which = "" if n == 1 else f"{int(bad.sum())} of {n} frames: "
        warnings.warn(
            f"{p}: {which}{100 * float(sat.max()):.2g} % of the footprint pixels are saturated "
            f"(at {full}); features will be biased low",
            CameraWarning,
            stacklevel=3,
        )
    blank = sub.max(axis=(1, 2)) == sub.min(axis=(1, 2))
    if blank.any():
        which = "" if n == 1 else f"{int(blank.sum())} of {n} frames "
        warnings.warn(f"{p}: {which}blank (all pixels {float(sub[blank][0].max()):g})", CameraWarning, stacklevel=3)

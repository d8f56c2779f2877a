"""Frame files as labs save them (camera/framefiles.py): multi-page TIFF stacks, 8/12/16-bit PNG
and TIFF, dropped pages warned about, mixed sizes and bit depths refused with one line."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tifffile
from PIL import Image, PngImagePlugin

from elastimap.camera.framefiles import CameraWarning, read_file, read_frames
from elastimap.camera.frames import read_frame, read_stack
from elastimap.errors import UserError

RNG = np.random.default_rng(39)


def frames(n, dtype=np.uint16, hi=None, shape=(12, 16)):
    hi = hi or (np.iinfo(dtype).max // 2)
    return RNG.integers(10, hi, (n, *shape)).astype(dtype)


def quiet():
    """No warning at all may be raised inside."""
    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error")
    return ctx


def test_ten_page_16bit_tiff_stack_reads_every_page(tmp_path):
    F = frames(10)
    p = tmp_path / "stack.tif"
    tifffile.imwrite(p, F, photometric="minisblack")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stack, full = read_stack([str(p)], (12, 16))
    assert stack.shape == (10, 12, 16) and full == 65535
    assert np.array_equal(stack, F.astype(float))
    # two files: every frame of each, in order
    q = tmp_path / "more.tif"
    tifffile.imwrite(q, F[:3], photometric="minisblack")
    both, _ = read_stack([str(p), str(q)])
    assert both.shape == (13, 12, 16) and np.array_equal(both[10:], F[:3].astype(float))


def test_reading_one_frame_of_a_stack_warns_that_pages_are_dropped(tmp_path):
    F = frames(10)
    p = tmp_path / "stack.tif"
    tifffile.imwrite(p, F, photometric="minisblack")
    with pytest.warns(CameraWarning, match=r"stack.tif: 9 of 10 frames dropped"):
        a, full = read_frame(p)
    assert np.array_equal(a, F[0].astype(float)) and full == 65535


@pytest.mark.parametrize("fmt", ["png", "tif"])
@pytest.mark.parametrize("dtype,full", [(np.uint8, 255), (np.uint16, 65535)])
def test_8_and_16_bit_png_and_tiff_round_trip(tmp_path, fmt, dtype, full):
    F = frames(1, dtype)
    p = tmp_path / f"f.{fmt}"
    if fmt == "png":
        Image.fromarray(F[0]).save(p)
    else:
        tifffile.imwrite(p, F[0], photometric="minisblack")
    a, fs = read_file(p)
    assert fs == full and a.shape == (1, 12, 16) and np.array_equal(a[0], F[0].astype(float))


def test_12_bit_png_with_sbit_reads_against_4095(tmp_path):
    F = frames(1, np.uint16, hi=4095)
    info = PngImagePlugin.PngInfo()
    info.add(b"sBIT", b"\x0c")
    p = tmp_path / "f12.png"
    Image.fromarray(F[0]).save(p, pnginfo=info)
    a, full = read_file(p)
    assert full == 4095 and np.array_equal(a[0], F[0].astype(float))


def test_12_bit_data_in_16_bit_containers_needs_the_cameras_bits(tmp_path):
    F = frames(3, np.uint16, hi=4095)
    p = tmp_path / "cam12.tif"
    tifffile.imwrite(p, F, photometric="minisblack")
    assert read_file(p)[1] == 65535  # nothing in the file says 12 bits
    stack, full = read_frames([str(p)], bits=12)
    assert full == 4095 and np.array_equal(stack, F.astype(float))
    hot = F.copy()
    hot[1, 0, 0] = 5000
    q = tmp_path / "hot.tif"
    tifffile.imwrite(q, hot, photometric="minisblack")
    with pytest.raises(UserError, match=r"hot.tif: values up to 5000 do not fit 12 bits"):
        read_frames([str(q)], bits=12)
    r = tmp_path / "eight.png"
    Image.fromarray(frames(1, np.uint8)[0]).save(r)
    assert read_frames([str(r)], bits=12)[1] == 255  # fewer bits than the camera: the file's own depth
    assert read_frames([str(p)], bits=16)[1] == 65535


def test_mixed_sizes_in_one_stack_are_refused(tmp_path):
    p = tmp_path / "mixed.tif"
    tifffile.imwrite(p, frames(1)[0], photometric="minisblack")
    tifffile.imwrite(p, frames(1, shape=(10, 16))[0], photometric="minisblack", append=True)
    with pytest.raises(
        UserError, match=r"mixed.tif: page 2 is 16x10 \(cols x rows\), page 1 16x12 .*mixed frame sizes"
    ):
        read_frames([str(p)])


def test_mixed_bit_depths_are_refused_within_and_across_files(tmp_path):
    p = tmp_path / "depths.tif"
    tifffile.imwrite(p, frames(1)[0], photometric="minisblack")
    tifffile.imwrite(p, frames(1, np.uint8)[0], photometric="minisblack", append=True)
    with pytest.raises(UserError, match=r"depths.tif: page 2 is uint8, page 1 uint16: mixed bit depths"):
        read_frames([str(p)])
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    Image.fromarray(frames(1)[0]).save(a)
    Image.fromarray(frames(1, np.uint8)[0]).save(b)
    with pytest.raises(UserError, match=r"b.png: bit depth differs from .*a.png"):
        read_frames([str(a), str(b)])


def test_reduced_resolution_previews_are_dropped_with_a_warning(tmp_path):
    F = frames(2)
    p = tmp_path / "preview.tif"
    tifffile.imwrite(p, F[0], photometric="minisblack")
    tifffile.imwrite(p, F[0][::2, ::2], photometric="minisblack", subfiletype=1, append=True)
    tifffile.imwrite(p, F[1], photometric="minisblack", append=True)
    with pytest.warns(CameraWarning, match=r"preview.tif: 1 reduced-resolution page\(s\) \(previews\) dropped; 2"):
        stack, _ = read_frames([str(p)])
    assert np.array_equal(stack, F.astype(float))


def test_colour_tiff_is_converted_to_grey_with_a_warning(tmp_path):
    rgb = RNG.integers(0, 255, (12, 16, 3)).astype(np.uint8)
    p = tmp_path / "rgb.tif"
    tifffile.imwrite(p, rgb, photometric="rgb")
    with pytest.warns(CameraWarning, match="rgb.tif: colour image"):
        a, full = read_file(p)
    grey = np.asarray(Image.fromarray(rgb).convert("L"), float)
    assert full == 255 and a.shape == (1, 12, 16) and np.abs(a[0] - grey).max() <= 1


def test_float_and_corrupt_files_are_refused_with_one_line(tmp_path):
    p = tmp_path / "float.tif"
    tifffile.imwrite(p, np.zeros((4, 4), np.float32))
    with pytest.raises(UserError, match="float.tif: floating-point images are not supported"):
        read_file(p)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00" + b"\xff" * 40)
    with pytest.raises(UserError, match="bad.tif: not a readable TIFF"):
        read_file(bad)
    with pytest.raises(UserError, match="no image files given"):
        read_frames([])


def test_saturated_frames_of_a_stack_are_counted(tmp_path):
    F = frames(4)
    F[2, :6, :] = 65535
    p = tmp_path / "sat.tif"
    tifffile.imwrite(p, F, photometric="minisblack")
    with pytest.warns(CameraWarning, match=r"sat.tif: 1 of 4 frames: .* saturated"):
        read_frames([str(p)])


def test_a_12_bit_camera_end_to_end(tmp_path):
    """SYNTHETIC 12-bit camera: frames rendered against 4095, saved as 16-bit PNG (no sBIT) and as
    one TIFF stack, give the same camera features as the frames themselves."""
    from elastimap.camera.features import camera_features, features_from_files
    from elastimap.camera.frames import write_frames
    from elastimap.camera.optics import SensorModel, render_pair
    from elastimap.solver.synthetic import solve_dhe  # SYNTHETIC stand-in, not physics

    m = SensorModel(bits=12).validate()
    res = solve_dhe(8.0, 7.0, 60.0)
    F, B = render_pair(m, res.image_raw, res.image, res.pixel, frames=4)
    assert F.dtype == np.uint16 and F.max() <= 4095 and m.full_scale == 4095
    want = camera_features(F.astype(float), B.astype(float), 4095, m.window, m.pixel_mm)
    pf = write_frames(F, tmp_path, "lesion", "png")
    pb = write_frames(B, tmp_path, "background", "png")
    got = features_from_files(pf, pb, m)
    assert got.O1 == want.O1 and got.O2 == want.O2 and got.O3 == want.O3
    tifffile.imwrite(tmp_path / "lesion.tif", F, photometric="minisblack")
    tifffile.imwrite(tmp_path / "background.tif", B, photometric="minisblack")
    stacked = features_from_files([str(tmp_path / "lesion.tif")], [str(tmp_path / "background.tif")], m)
    assert (stacked.O1, stacked.O2, stacked.O3) == (want.O1, want.O2, want.O3)


def test_packed_12_bit_tiff_stack_reads_against_4095(tmp_path):
    """A packed 12-bit TIFF (BitsPerSample 12, three bytes for two pixels) says its depth itself;
    reading it needs the optional imagecodecs (pyproject, extra ``frames``)."""
    pytest.importorskip("imagecodecs")
    F = frames(4, np.uint16, hi=4095)
    p = tmp_path / "packed12.tif"
    tifffile.imwrite(p, F, photometric="minisblack", bitspersample=12)
    with tifffile.TiffFile(p) as tif:
        pg = tif.pages[0]
        assert pg.bitspersample == 12 and sum(pg.databytecounts) == 12 * 16 * 12 // 8  # packed, not 16-bit containers
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing dropped, nothing to warn about
        stack, full = read_frames([str(p)])
    assert full == 4095 and np.array_equal(stack, F.astype(float))

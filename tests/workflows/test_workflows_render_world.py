"""The world renderer (:mod:`elastimap.workflows.render_world`) on a SYNTHETIC four-phantom world: the
tables it writes are read by the product's own readers (a measured set, a calibration's camera CSV)."""

import csv

import numpy as np
from click.testing import CliRunner

from elastimap.workflows import render_world


def _world(tmp_path):
    w = tmp_path / "world"
    w.mkdir()
    yy, xx = np.mgrid[-12.25:12.3:0.5, -12.25:12.3:0.5]
    ref = 3.0 - 0.002 * (xx**2 + yy**2)
    rows = []
    for i, (d, h, E) in enumerate([(6, 7, 60), (10, 8, 30), (4, 6, 30), (8, 7, 50)], start=1):
        raw = ref + 0.05 * d / 10 * np.exp(-(xx**2 + yy**2) / (2 * (d / 2) ** 2))
        np.save(w / f"raw_{i}.npy", raw)
        np.save(w / f"ref_{i}.npy", ref)
        rows.append(["none", f"P{i:02d}", d, h, E, f"raw_{i}.npy", f"ref_{i}.npy", 1, 1, "no effect"])
    with open(w / "sets.csv", "w", newline="") as f:
        c = csv.writer(f)
        c.writerow(
            ["set", "phantom", "d_mm", "h_mm", "E_kPa", "raw", "ref", "plate_force_mN", "plate_force_ref_mN", "effect"]
        )
        c.writerows(rows)
    return w


def test_rendered_set_is_a_measured_set(tmp_path):
    from elastimap.gap.measured import load

    w = _world(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(render_world.cli, ["--world", str(w), "--frames", "2", "--out", str(out)])
    assert r.exit_code == 0, r.output
    m = load(out / "none")
    assert m.ids == ["P01", "P02", "P03", "P04"]
    assert np.allclose(m.dhe[:2], [[6, 7, 60], [10, 8, 30]])
    # the larger bump gives the larger peak feature
    assert m.y[1, 0] > m.y[3, 0] > m.y[0, 0] > m.y[2, 0] > 0
    assert sorted(p.name for p in (out / "none").iterdir()) == [
        "camera.csv",
        "frames",
        "lesions.csv",
        "measured.csv",
        "phantoms.csv",
    ]


def test_refuses_existing_out_and_unknown_set(tmp_path):
    w = _world(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    r = CliRunner().invoke(render_world.cli, ["--world", str(w), "--out", str(out)])
    assert r.exit_code == 2 and "--out" in r.output
    r = CliRunner().invoke(render_world.cli, ["--world", str(w), "--sets", "nope", "--out", str(tmp_path / "o2")])
    assert r.exit_code == 2 and "--sets" in r.output
    assert not (tmp_path / "o2").exists() and list(out.iterdir()) == []


def test_lens_k1_renders_through_a_distorting_camera(tmp_path):
    """``--lens-k1`` images the presses through that lens: the same noise, other frames; 0 is the
    nominal camera's frames bit for bit; beyond the allowed range a one-line error (exit 2)."""
    from elastimap.camera.frames import read_stack

    w = _world(tmp_path)
    outs = {}
    for k in ("0", "-0.15"):
        outs[k] = tmp_path / f"out{k}"
        r = CliRunner().invoke(
            render_world.cli, ["--world", str(w), "--frames", "2", "--lens-k1", k, "--out", str(outs[k])]
        )
        assert r.exit_code == 0, r.output
    plain = tmp_path / "plain"
    assert (
        CliRunner().invoke(render_world.cli, ["--world", str(w), "--frames", "2", "--out", str(plain)]).exit_code == 0
    )
    pattern = "synthetic_P02_lesion_f*.png"
    a, b, c = (
        read_stack([str(p) for p in sorted((o / "none" / "frames").glob(pattern))])[0]
        for o in (plain, outs["0"], outs["-0.15"])
    )
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    r = CliRunner().invoke(render_world.cli, ["--world", str(w), "--lens-k1", "-0.3", "--out", str(tmp_path / "o3")])
    assert r.exit_code == 2 and "--lens-k1" in r.output

"""``verify_morph --checks calculix``: an independent model's phantoms by the remeshed/fixed and the
morphed/by_d paths, each one's deviation from the table (tiny mesh, one phantom)."""

from __future__ import annotations

import pytest

from elastimap.solver.verify_morph import check_calculix, main

ROW = "d_mm,h_mm,E_kPa,O1_mm,O2_mm,plate_force_mN,plate_force_ref_mN,nodes\n8.0,7.0,50.0,0.0279,7.68,1371.1,1339.6,1\n"


def test_calculix_check_solves_each_phantom_by_both_paths(tmp_path):
    table = tmp_path / "ccx.csv"
    table.write_text(ROW)
    text = check_calculix(table, mesh="tiny")
    rows = [line for line in text.splitlines() if line.startswith("| 8 | 7 | 50 |")]
    assert [r.split("|")[4].strip() for r in rows] == ["O1", "O2", "force", "force_ref"]
    for r in rows:
        cells = [c.strip() for c in r.strip("|").split("|")]
        a, b = (abs(float(c.rstrip(" %"))) for c in cells[5:7])
        if a != b:  # (equal when rounded to the printed 0.01 %)
            assert cells[7] == ("remesh/fixed" if a < b else "morph/by_d")
    assert "| O1 and O2 |" in text


def test_calculix_check_needs_the_table(capsys):
    with pytest.raises(SystemExit) as ex:
        main(["--checks", "calculix"])
    assert ex.value.code == 2
    assert "--calculix" in capsys.readouterr().err

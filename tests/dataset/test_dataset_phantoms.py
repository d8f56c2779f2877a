"""The one phantom-table reader (dataset/phantoms.py): the shipped table, a user's, and bad tables."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.dataset import phantoms as P
from elastimap.errors import UserError


def test_shipped_table_is_the_papers_nine_inclusions():
    t = P.read_phantoms()
    assert list(t["name"])[:3] == ["size-1", "size-2", "size-3"] and len(t) == 9
    assert set(t["phantom"]) == {"size", "depth", "hardness"}
    assert (t["tissue_E"] == 5.0).all() and (t["tissue_thickness"] == 20.0).all()
    assert t.loc[t["name"] == "depth-3", ["d", "h", "E"]].to_numpy().tolist() == [[8.0, 12.0, 80.0]]


def test_phantom_samples_tags_and_ids():
    rows = P.phantom_samples()
    assert rows[0] == {
        "sample_id": "phantom-size-1",
        "tag": "phantom:size-1",
        "d": 5.0,
        "h": 8.0,
        "E": 80.0,
        "tissue_E": 5.0,
        "tissue_thickness": 20.0,
    }
    assert P.is_phantom([r["tag"] for r in rows]).all()
    assert P.is_phantom(["phantom:x", "design", "phantom", "user"]).tolist() == [True, False, False, False]
    assert P.phantom_name("phantom:depth-2") == "depth-2"
    with pytest.raises(ValueError):
        P.phantom_name("design")


def test_user_table_with_ids_and_no_tissue_columns(tmp_path):
    f = tmp_path / "mine.csv"
    f.write_text("# my lab's phantoms\nid,d,h,E\n7,6,8,40\nb , 9, 10, 90\n")
    t = P.read_phantoms(f)
    assert list(t["name"]) == ["7", "b"] and t["E"].tolist() == [40.0, 90.0]
    assert P.phantom_samples(t)[1] == {"sample_id": "phantom-b", "tag": "phantom:b", "d": 9.0, "h": 10.0, "E": 90.0}


@pytest.mark.parametrize(
    "text,needle",
    [
        (None, "no such file"),
        ("name,d,h\na,1,2\n", "missing column(s) E"),
        ("name,d,h,E\na,1,2,3\na,1,2,3\n", "duplicate names ['a']"),
        ("name,d,h,E\n,1,2,3\n", "every row needs a name"),
        ("name,d,h,E\na,1,2,3\nb,-1,2,3\n", "column d must be positive numbers (mm)"),
        ("name,d,h,E\na,1,2,x\n", "column E must be positive numbers (kPa)"),
        ("name,d,h,E,tissue_E\na,1,2,3,0\n", "column tissue_E must be positive"),
        ("name,d,h,E\na,1,nan,3\n", "column h must be positive"),
        ("", "not a readable CSV"),
        ("name,d,h,E\n", "need at least 1 inclusion"),
    ],
)
def test_bad_table_is_one_user_error(tmp_path, text, needle):
    f = tmp_path / "ph.csv"
    if text is not None:
        f.write_text(text)
    with pytest.raises(UserError) as e:
        P.read_phantoms(f, param="phantoms")
    assert e.value.param == "phantoms" and needle in e.value.message and "\n" not in e.value.message


def test_too_few_rows_says_why(tmp_path):
    f = tmp_path / "ph.csv"
    f.write_text("name,d,h,E\na,1,2,3\nb,2,2,3\n")
    with pytest.raises(UserError, match=r"need at least 3 inclusion\(s\) to fit a line \(got 2\)"):
        P.read_phantoms(f, param="phantoms", min_rows=3, why="to fit a line")
    assert len(P.read_phantoms(f, min_rows=2)) == 2


def test_a_folder_is_not_a_table(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        P.read_phantoms(tmp_path)


def test_training_and_plots_use_the_reader():
    from elastimap.training.data import prepare, synthetic_table

    s = prepare(synthetic_table(40, seed=1), source="SYNTHETIC")
    assert "9 calibration-phantom row(s)" in s.report()
    assert np.sum(P.is_phantom(s.df["tag"])) == 9


#: readers that still spell the phantom tag or read the table themselves; they switch to
#: elastimap.dataset.phantoms when issue 37 merges, and this set then empties
PENDING: set[str] = set()


def test_one_phantom_reader():
    """Only dataset/phantoms.py spells the ``phantom:`` tag or defines a phantom-table reader."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    found = set()
    for room in ("elastimap", "solver", "dataset", "sweep", "training", "identify", "camera", "gap", "workflows"):
        for path in (root / room).rglob("*.py"):
            rel = path.relative_to(root).as_posix()
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Constant) and node.value == P.TAG_PREFIX:
                    found.add(rel)
                if isinstance(node, ast.FunctionDef) and node.name in ("load_phantoms", "read_phantoms"):
                    found.add(rel)
    assert found - PENDING == {"dataset/phantoms.py"}

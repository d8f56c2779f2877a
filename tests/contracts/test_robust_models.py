"""A model folder whose ranges are damaged is refused on load; a saved model folder follows the umask.

Before: a ``model.json`` with a NaN ``feature_range`` or a ``target_range`` whose minimum exceeds
its maximum loaded, and the range flags of ``infer`` silently vanished; ``Ensemble.save`` left
its folder 0700 (``tempfile.mkdtemp``) whatever the umask.
"""

from __future__ import annotations

import json
import os
import shutil
import stat

import pytest
from test_bad_inputs import make_model

from elastimap.errors import UserError
from elastimap.training.model import Ensemble


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    old = os.umask(0o022)
    try:
        return make_model(tmp_path_factory.mktemp("m") / "model")
    finally:
        os.umask(old)


def test_saved_model_folder_follows_the_umask(model):
    assert stat.S_IMODE(model.stat().st_mode) == 0o755
    assert {stat.S_IMODE(p.stat().st_mode) for p in model.iterdir()} == {0o644}


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d["feature_range"][0].__setitem__(0, float("nan")),
        lambda d: d["feature_range"][1].__setitem__(2, float("inf")),
        lambda d: d.update(target_range=[d["target_range"][1], d["target_range"][0]]),
    ],
    ids=["nan-feature-range", "inf-feature-range", "min-above-max-target-range"],
)
def test_damaged_ranges_are_refused(model, tmp_path, edit):
    bad = tmp_path / "model"
    shutil.copytree(model, bad)
    doc = json.loads((bad / "model.json").read_text())
    edit(doc)
    (bad / "model.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match="range") as ei:
        Ensemble.load(str(bad))
    assert ei.value.param == "model" and "\n" not in str(ei.value)

"""The studies' one registry and the image-model study's refusals (SYNTHETIC data, no solver)."""

from __future__ import annotations

import pkgutil

import numpy as np
import pytest
from click.testing import CliRunner

from elastimap.cli import cli
from elastimap.cli_util import run
from elastimap.workflows import studies
from elastimap.workflows.studies import STUDIES


def test_every_study_module_is_in_the_one_registry_and_runs_under_elastimap_study():
    modules = {m.name for m in pkgutil.iter_modules(studies.__path__)}
    assert modules == set(STUDIES)
    r = CliRunner().invoke(cli, ["study", "-h"])
    assert r.exit_code == 0 and all(f"\n  {name} " in r.output for name in STUDIES), r.output
    assert "identify" not in CliRunner().invoke(cli, ["--help"]).output.split("Commands:")[1]


def _data(n: int = 24):
    """SYNTHETIC lesions: a Gaussian bump whose width follows d, depth-damped amplitude."""
    from elastimap.identify.measure import Data

    rng = np.random.default_rng(0)
    d, h, E = rng.uniform(3, 12, n), rng.uniform(4, 12, n), np.exp(rng.uniform(np.log(10), np.log(200), n))
    y, x = np.mgrid[0:8, 0:8] * 0.5
    amp = 1e-3 * d**2 / h * (E / (E + 20))
    images = amp[:, None] * np.exp(-(x.ravel() ** 2 + y.ravel() ** 2)[None] / (2 * (0.5 * d + 0.3 * h)[:, None] ** 2))
    feats = np.column_stack([amp, images.sum(1), np.ones(n)])
    return Data(
        theta=np.column_stack([d, h, E]),
        features=feats,
        images=images,
        dforce=amp,
        force_ref=np.ones(n),
        tags=np.array(["phantom:p0"] * 3 + ["design"] * (n - 3)),
        ids=np.array([f"s{i:04d}" for i in range(n)]),
        shape=(8, 8),
        pixel=0.5,
        source="SYNTHETIC",
    )


def test_image_model_study_refuses_a_too_large_net_naming_a_flag_it_has_and_writes_nothing(
    tmp_path, monkeypatch, capsys
):
    """Too few rows for the network: one line naming --hidden (a flag of this command), and no
    empty --out left behind."""
    import elastimap.identify.measure as measure
    from elastimap.workflows.studies import image_model

    monkeypatch.setattr(measure, "load", lambda path, design_only=False: _data())
    out = tmp_path / "runs" / "img"

    def refused(*args) -> str:
        with pytest.raises(SystemExit) as exc:
            run(image_model.main, ["--data", "x", *args, "--out", str(out)], prog_name="elastimap study image_model")
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
        return err

    assert "--hidden" in refused("--hidden", "40,20", "--repeats", "1", "--no-progress")
    assert "--hidden" in [o for p in image_model.main.params for o in p.opts]
    assert not out.exists() and not (tmp_path / "runs").exists()
    assert "--hidden" in refused("--hidden", "x")
    assert not out.exists()

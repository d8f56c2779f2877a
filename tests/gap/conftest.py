"""Fixtures shared by the gap tests."""

import numpy as np
import pytest

from elastimap.gap import effects as fx
from elastimap.gap.candidates import Candidate
from elastimap.gap.fit_models import Single
from elastimap.gap.simulate import Simulator

#: the grids of the SYNTHETIC linear effects of :func:`linear_world`
LINEAR_GRIDS = {
    "friction": np.linspace(0, 1, 5),
    "nonlinearity": np.linspace(0, 1, 5),
    "indentation": np.linspace(-0.6, 0.6, 7),
    "gamma": np.linspace(0.7, 1.4, 8),
}


@pytest.fixture(scope="module")
def toy():
    """The TOY (analytic) simulator on the tiny mesh: fast, SYNTHETIC, no DOLFINx solve."""
    return Simulator(None, "tiny", "toy")


def _linear_sweep(name, grid, y0, direction):
    """A SYNTHETIC linear effect: f(θ) = y0 + (θ − nominal) · direction on every phantom."""
    e = fx.get(name)
    g = np.asarray(grid, float)
    V = {"profile": y0[None] + (g - e.nominal)[:, None, None] * direction[None]}
    return Candidate(e, g, V, None)


def _linear_world(seed=0, n=10, Q=8, effects=("friction", "nonlinearity", "indentation")):
    """A SYNTHETIC world of hand-made linear sweeps (not physics): ``(rng, y0, dirs, models)`` with
    the baseline y0 (n phantoms × Q values), each effect's direction and its one-parameter model;
    ``rng`` continues the stream for the data's noise."""
    rng = np.random.default_rng(seed)
    y0 = rng.uniform(50, 100, (n, Q))
    dirs = {k: rng.standard_normal((n, Q)) * 8 for k in effects}
    models = [Single(_linear_sweep(k, LINEAR_GRIDS[k], y0, d), ["profile"]) for k, d in dirs.items()]
    return rng, y0, dirs, models


@pytest.fixture(scope="session")
def linear_world():
    """:func:`_linear_world`, the SYNTHETIC linear-sweep world of the selection tests."""
    return _linear_world

"""Fixtures shared by the gap tests."""

import pytest

from elastimap.gap.simulate import Simulator


@pytest.fixture(scope="module")
def toy():
    """The TOY (analytic) simulator on the tiny mesh: fast, SYNTHETIC, no DOLFINx solve."""
    return Simulator(None, "tiny", "toy")

"""The diagnosis's settings (:class:`Settings`) and the mesh ladder of its model error (:data:`FINER`).

Every field is fixed before any data are seen; nothing is tuned on the data scored
(docs/gap.md, 'Method').
"""

from __future__ import annotations

from dataclasses import dataclass

from elastimap.solver.params import MESH_LEVELS, finer

from . import effects as fx

#: the meshes a diagnosis runs on and each one's default error mesh, the next finer level; ``fine`` has
#: none (its next level, ``finer``, is too costly to solve for every phantom and candidate)
FINER = {level: finer(level) if level != "fine" else None for level in MESH_LEVELS if level != "finer"}


@dataclass
class Settings:
    alpha: float = 0.01  # level of the calibrated χ² tests
    ambiguity_margin: float = 4.6  # Δscore below which candidates cannot be told apart (2 ln 10)
    model_floor: float = 0.005  # relative model error, used only without a second mesh level
    order_image: float = 3.0  # convergence order p of features and profile (measured)
    order_force: float = 1.0  # convergence order p of the plate force (measured)
    richardson: bool = True  # correct the model by its Richardson estimate; σ = its spread over the orders below
    order_range_image: tuple = (2.0, 4.0)  # orders p bracketing the measured image order (3.4-3.8)
    order_range_force: tuple = (0.75, 1.5)  # orders p bracketing the measured force order (about 1)
    force_noise: float = 0.01  # relative standard error assumed for a plate-force gauge (proposals)
    second_delta: float = 4.5  # mm, the second indentation depth a proposal considers
    propose_phantoms: int = 4  # phantoms solved at the second depth
    propose_solves: bool = True  # run the solves that check a proposal
    families: tuple = fx.DEFAULT_FAMILIES
    bootstrap: int = 200
    seed: int = 0
    adaptive: bool = True  # mechanics magnitudes: sensitivity solve + refinement near the fit (else the grid)
    refine_rounds: int = 3  # at most this many refinement rounds
    refine_top: int = 2  # refine the best this many candidates ...
    refine_margin: float = 9.2  # ... and every one within this Δscore of the best (2 x ambiguity_margin)
    refine_extrapolated: int = 2  # ... and the best this many whose fit is extrapolated (beyond the solved magnitudes)
    refine_tol: float = 0.03  # a fit within this fraction of the effect's range of a solved magnitude is not re-solved
    model_form: bool = True  # the model-form level in the decision (gap/model_form.py; False: the closed world)
    pair_top: int = 5  # pairs: each of the best this many single effects with every other one (< 1: none)
    pair_beside_single: bool = False  # a pair may lead beside a passing single (default: only when none passes)
    inverse: bool = True
    n_train: int = 40
    train_repeats: int = 4
    train_epochs: int = 300

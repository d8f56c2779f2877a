"""The solver's failure type (no DOLFINx import: callers can catch it cheaply)."""


class SolverError(RuntimeError):
    """A solve failed (no convergence, singular system, bad mesh); carries the parameters."""

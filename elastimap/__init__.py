"""elastimap: shared, dependency-free pieces used by every stage.

The stages themselves live in the top-level packages ``solver`` (geometry and
FEM solve), ``sweep`` (batch runs), ``dataset`` (Parquet schema and tools),
``training`` (MLP inverse), ``camera`` (optical sensor side) and ``gap``
(sim-to-real diagnosis).  This package only holds what all of them share:
the user-error type and the CLI wrapper that turns it into a one-line message
with exit code 2, and the code version stamped into provenance.
"""

__version__ = "0.1.0"

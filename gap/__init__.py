"""Sim-to-real gap diagnosis (issue 6): where the gap lies, which unmodelled effect causes it,
how far it shrinks once the effect is added, and a blind self-test on withheld effects.

Modules: :mod:`gap.effects` (effects library), :mod:`gap.simulate` (cached forward solves and
camera features), :mod:`gap.measured` (measured-data format), :mod:`gap.synth` (SYNTHETIC
measured data), :mod:`gap.diagnose` (the analysis), :mod:`gap.report` (Markdown/PNG/JSON),
:mod:`gap.selftest` (blind check), :mod:`gap.cli`.  See docs/gap.md.
"""

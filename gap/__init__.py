"""Sim-to-real gap diagnosis (issue 6): where the gap lies, which unmodelled effect causes it,
how far it shrinks once the effect is added, and a blind self-test on withheld effects.

Modules: :mod:`elastimap.gap.effects` (effects library), :mod:`elastimap.gap.simulate` (cached forward solves and
camera features), :mod:`elastimap.gap.measured` (measured-data format), :mod:`elastimap.gap.synth` (SYNTHETIC
measured data), :mod:`elastimap.gap.diagnose` (the analysis), :mod:`elastimap.gap.report` (Markdown/PNG/JSON),
:mod:`elastimap.gap.selftest` (blind check), :mod:`elastimap.gap.cli`.  See docs/gap.md.
"""

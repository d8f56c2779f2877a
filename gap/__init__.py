"""Sim-to-real gap diagnosis: is there a gap beyond the model's own tolerance, which unmodelled
effect(s) explain it, where it lies, how far it shrinks, which measurement would separate
look-alike effects, and a blind benchmark on data from another discretisation.

Modules: :mod:`elastimap.gap.effects` (effects library and families), :mod:`elastimap.gap.simulate`
(cached forward solves and camera features), :mod:`elastimap.gap.views` (features, image profile,
force; noise from frames), :mod:`elastimap.gap.measured` (measured-data format),
:mod:`elastimap.gap.synth` (SYNTHETIC measured data), :mod:`elastimap.gap.diagnose` (the analysis's
driver; its steps: candidates, model_error, adaptive, fit_models, selection, where, propose, shrink;
settings), :mod:`elastimap.gap.report` (Markdown/HTML/PNG/JSON), :mod:`elastimap.gap.selftest` (blind benchmark),
:mod:`elastimap.gap.bench` (timing of a first diagnosis), :mod:`elastimap.gap.cli`.  See docs/gap.md.
"""

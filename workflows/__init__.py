"""Reproducible pipelines built on the stages (installed as ``elastimap.workflows``).

``paper_table.py`` (the paper's error table end to end), ``slurm_cluster.py`` with ``sweep.sbatch``
(sweeps on a SLURM cluster), :mod:`elastimap.workflows.benchmarks` (the SYNTHETIC camera-frame
benchmark, ``frames_benchmark.py`` as a script) and :mod:`elastimap.workflows.studies`, the studies
behind the shipped map, the deployed image model, the calibrated intervals and the docs' tables
(``elastimap study <name>``).  Nothing in the stages imports
this package.
"""

"""Reproducible pipelines built on the stages (installed as ``elastimap.workflows``).

``paper_table.py`` (the paper's error table end to end), ``slurm_cluster.py`` with ``sweep.sbatch``
(sweeps on a SLURM cluster) and :mod:`elastimap.workflows.studies`, the identifiability studies
behind the shipped map and the tables of docs/identifiability.md.  Nothing in the stages imports
this package.
"""

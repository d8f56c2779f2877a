"""Every option of the solver's and the sweep's commands says what it does (``--help``), and the
one progress switch is ``--no-progress``."""

import click
import pytest

from elastimap.solver.cli import command as solve_cmd
from elastimap.solver.verify import command as verify_cmd
from elastimap.solver.verify_morph import command as verify_morph_cmd
from elastimap.sweep.cli import cli as sweep_cli


def _options(cmd, name):
    if isinstance(cmd, click.Group):
        for sub, c in cmd.commands.items():
            yield from _options(c, f"{name} {sub}")
    else:
        for p in cmd.params:
            if isinstance(p, click.Option):
                yield name, p


@pytest.mark.parametrize(
    "cmd, name",
    [(solve_cmd, "solve"), (sweep_cli, "sweep"), (verify_cmd, "verify"), (verify_morph_cmd, "verify_morph")],
)
def test_every_option_has_help_and_one_progress_switch(cmd, name):
    missing = [f"{where} {'/'.join(p.opts)}" for where, p in _options(cmd, name) if not (p.help or "").strip()]
    assert not missing, missing
    progress = {o for _w, p in _options(cmd, name) for o in p.opts if "progress" in o or o in ("--quiet", "-q")}
    assert progress <= {"--no-progress"}, progress

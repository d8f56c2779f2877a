"""One way of naming things on every command line (issue 37): help on every option, ``--out`` for
every output path, ``--no-progress`` the one progress switch, and each room's click root named ``cli``
with a ``main(argv=None)`` entry (elastimap/cli_util.py's module docstring).

``ROOMS`` lists the rooms that follow the convention; a room joins the list when it does.
"""

from __future__ import annotations

import importlib
import inspect

import click
import click.testing
import pytest

#: room CLI modules that follow the convention (each has ``cli`` and ``main(argv=None)``)
ROOMS = (
    "elastimap.dataset.cli",
    "elastimap.training.cli",
    "elastimap.training.bench",
    "elastimap.camera.cli",
    "elastimap.gap.cli",
    "elastimap.sweep.cli",
    "elastimap.solver.cli",
)
#: flags that mean the same as a shared one and must not come back
RETIRED = {"--quiet": "--no-progress", "--progress": "--no-progress", "--csv": "--out"}
#: where a retired spelling means something else: ``infer --csv`` reads a batch table (an input, not an output)
ALLOWED = {("elastimap.camera.cli", "--csv")}


def _commands(cmd: click.Command, path: tuple[str, ...] = ()):
    yield path, cmd
    if isinstance(cmd, click.Group):
        for name, sub in cmd.commands.items():
            yield from _commands(sub, (*path, name))


@pytest.mark.parametrize("module", ROOMS)
def test_root_is_cli_and_main_takes_argv(module):
    m = importlib.import_module(module)
    assert isinstance(m.cli, click.Command)
    assert list(inspect.signature(m.main).parameters) == ["argv"]


@pytest.mark.parametrize("module", ROOMS)
def test_every_option_has_help_and_no_retired_flag(module):
    root = importlib.import_module(module).cli
    for path, cmd in _commands(root):
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.name == "help":
                continue
            where = f"{module} {' '.join(path)} {p.opts[0]}"
            assert p.help and p.help.strip(), f"{where}: no help text"
            for flag in p.opts + p.secondary_opts:
                if (module, flag) not in ALLOWED:
                    assert flag not in RETIRED, f"{where}: {flag} is {RETIRED[flag]} everywhere else"


@pytest.mark.parametrize("module", ROOMS)
def test_progress_switch_is_the_shared_one(module):
    root = importlib.import_module(module).cli
    flags = {f for _, c in _commands(root) for p in c.params for f in getattr(p, "opts", [])}
    progress = {f for f in flags if "progress" in f or f == "--quiet"}
    assert progress <= {"--no-progress"}


def test_no_progress_option_is_a_flag_named_no_progress():
    from elastimap.cli_util import no_progress_option

    @click.command()
    @no_progress_option()
    def c(no_progress):
        click.echo(repr(no_progress))

    r = click.testing.CliRunner()
    assert r.invoke(c, []).output.strip() == "False"
    assert r.invoke(c, ["--no-progress"]).output.strip() == "True"

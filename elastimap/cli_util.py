"""The command-line layer shared by every command: one runner, the shared options, lazy groups.

Naming, the same in every room: a room's ``cli.py`` names its click root (group or command) ``cli``
and its console-script entry ``main(argv=None)``, which calls :func:`run`; the umbrella's stage
table points at ``elastimap.<room>.cli:cli``.  A room with more than one console script names the
extra entries ``<script>_main`` (``calibrate_main``).

Every console script and ``python -m`` entry of the project goes through :func:`run`:

* :class:`elastimap.errors.UserError` and click usage errors print
  ``error: <flag>: <message>`` on stderr and exit with 2 (no traceback).  Libraries
  name the *Python* parameter (``jobs``, ``batch_rows``, ``tissue.E``); :func:`flag_for`
  turns it into the flag of the command that ran (``--jobs``, ``--batch-rows``,
  ``--tissue-E``), so the translation lives here and nowhere else;
* ``-h`` and ``--help`` work on every command and group;
* every ``float`` option refuses ``nan`` and ``inf`` and every ``int`` option a number beyond 64
  bits, where it is typed (:func:`guard_numbers`);
* ``KeyboardInterrupt`` exits with 130;
* anything else is a bug and keeps its traceback.

The options several commands share are defined once here (:func:`mesh_option`,
:func:`out_option`, :func:`data_option`, :func:`jobs_option`, :func:`shard_option`,
:func:`no_progress_option`), and :class:`LazyGroup`
imports a subcommand's module only when that subcommand runs, so ``elastimap --help``
or a mistyped flag answers without importing torch, DOLFINx, dask or pandas.

This module imports only click and the standard library.
"""

from __future__ import annotations

import fnmatch
import importlib
import math
import sys

import click

from .errors import UserError

#: ``context_settings`` of every command and group: ``-h`` everywhere, wide help.
CONTEXT_SETTINGS = {"help_option_names": ["-h", "--help"], "max_content_width": 100}


# ----------------------------------------------------------------------------- shared options
class Choice(click.Choice):
    """``click.Choice`` whose error reads like a :class:`UserError`: ``must be one of a, b (got 'x')``."""

    def get_invalid_choice_message(self, value, ctx) -> str:
        return f"must be one of {', '.join(map(str, self.choices))} (got {value!r})"


class MeshLevel(Choice):
    """The solver's mesh levels, read from ``elastimap.solver.params`` (no DOLFINx) when first needed,
    so that declaring ``--mesh`` imports nothing."""

    name = "mesh level"

    def __init__(self):
        super().__init__(())

    @property
    def choices(self) -> tuple[str, ...]:
        from elastimap.solver.params import MESH_LEVELS

        return tuple(MESH_LEVELS)

    @choices.setter
    def choices(self, value) -> None:  # click.Choice.__init__ assigns it; the levels come from the solver
        pass


def mesh_option(
    default: str | None = "default", help: str = "Mesh level of the forward model (tiny is for tests only).", **kw
):
    """``--mesh``: a checked choice of the solver's mesh levels, the same on every command."""
    return click.option("--mesh", type=MeshLevel(), default=default, show_default=default is not None, help=help, **kw)


def geometry_option(
    default: str = "remesh",
    help: str = "remesh = a gmsh mesh for every (d, h); morph = a reference mesh moved to (d, h) (smooth in d, h).",
    **kw,
):
    """``--geometry``: how the mesh follows the inclusion (:mod:`elastimap.solver.morph`)."""
    from elastimap.solver.params import GEOMETRIES

    return click.option("--geometry", type=Choice(GEOMETRIES), default=default, show_default=True, help=help, **kw)


def sizing_option(
    default: str = "fixed",
    help: str = "Element size near the inclusion: fixed = the first sweeps' rule; by_d = scaled with d (converged).",
    flag: str = "--sizing",
    **kw,
):
    """``--sizing`` (or ``flag``): the element-size rule near the inclusion (:mod:`elastimap.solver.geometry`)."""
    from elastimap.solver.params import SIZINGS

    return click.option(flag, type=Choice(SIZINGS), default=default, show_default=True, help=help, **kw)


def _path_kw(default: str | None, required: bool) -> dict:
    # click >= 8.2 does not enforce required=True on an option given an explicit default=None
    kw = dict(required=required, show_default=default is not None, callback=_not_empty)
    return kw if default is None else {**kw, "default": default}


def _not_empty(ctx: click.Context, param: click.Parameter, value):
    """A path option given as '' is refused where it is typed (it would mean the current folder
    or the default, silently)."""
    if value is not None and not str(value).strip():
        raise click.BadParameter("must name a file or folder (got an empty string)", ctx, param)
    return value


def out_option(help: str = "Output directory.", default: str | None = None, required: bool = False, **kw):
    """``--out``: where results go (each command checks it before any work starts)."""
    return click.option("--out", "out", help=help, **_path_kw(default, required), **kw)


def data_option(
    help: str = "Sample dataset: a Parquet file or a sweep directory.",
    default: str | None = None,
    required: bool = False,
    **kw,
):
    """``--data``: the sample table a command reads (a sweep's output)."""
    return click.option("--data", "data", help=help, **_path_kw(default, required), **kw)


def no_progress_option(help: str = "Hide the progress bars (the results do not change).", **kw):
    """``--no-progress``: the one progress switch of every command; the value (``no_progress``) is
    ``True`` when given, so a library takes ``progress=not no_progress``."""
    return click.option("--no-progress", "no_progress", is_flag=True, default=False, help=help, **kw)


def jobs_option(default: int = 1, help: str = "Worker processes.", **kw):
    """``--jobs``: parallel worker processes (checked by the library that uses it, named ``jobs``)."""
    return click.option("--jobs", "jobs", type=int, default=default, show_default=True, help=help, **kw)


class Shard(click.ParamType):
    """``K/N`` -> ``(K, N)`` with 0 <= K < N: this process takes the items i with i % N == K."""

    name = "K/N"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        try:
            k, n = (int(v) for v in str(value).split("/"))
            if 0 <= k < n:
                return k, n
        except ValueError:
            pass
        self.fail(f"must be K/N with 0 <= K < N (got {value!r})", param, ctx)


def shard_option(help: str = "K/N: this process takes the items i with i % N == K.", **kw):
    """``--shard K/N``: split a resumable job between processes; the value is ``(K, N)``."""
    return click.option("--shard", type=Shard(), default="0/1", show_default=True, help=help, **kw)


class FiniteFloat(click.types.FloatParamType):
    """A float option that is finite: ``nan`` and ``inf`` are refused where they are typed
    (docs/errors.md, "Rules every command follows")."""

    def convert(self, value, param, ctx):
        v = super().convert(value, param, ctx)
        if not math.isfinite(v):
            self.fail(f"must be a finite number (got {value!r})", param, ctx)
        return v


class Int64(click.types.IntParamType):
    """An integer option that fits in 64 bits: a 20-digit number is refused where it is typed,
    not deep inside numpy after the work."""

    def convert(self, value, param, ctx):
        v = super().convert(value, param, ctx)
        if not -(2**63) <= v < 2**63:
            self.fail(f"must be an integer of at most 19 digits (got {value!r})", param, ctx)
        return v


_SAFE_TYPES = {click.types.FloatParamType: FiniteFloat(), click.types.IntParamType: Int64()}


def _safe_type(t: click.ParamType) -> click.ParamType:
    if type(t) in _SAFE_TYPES:
        return _SAFE_TYPES[type(t)]
    if isinstance(t, click.Tuple):
        t.types = [_safe_type(x) for x in t.types]
    return t


def guard_numbers(command: click.Command) -> click.Command:
    """Give every plain ``float`` / ``int`` option of ``command`` (and of the subcommands it holds)
    the finite / 64-bit types above; :func:`run` and :class:`LazyGroup` call it, so every command
    of the project refuses ``nan``, ``inf`` and 20-digit integers the same way, in one place."""
    for p in command.params:
        p.type = _safe_type(p.type)
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            guard_numbers(sub)
    return command


def options(*decorators):
    """Apply several option decorators in the order they are listed (first = first in --help)."""

    def deco(f):
        for d in reversed(decorators):
            f = d(f)
        return f

    return deco


def param_flags(mapping: dict[str, str]):
    """Attach extra Python-name -> flag rules to a command (``fnmatch`` patterns allowed),
    for library names that do not follow from the command's own parameters
    (``{"probe.layer*": "--layers"}``)."""

    def deco(cmd: click.Command) -> click.Command:
        cmd.param_flags = dict(mapping)
        return cmd

    return deco


# ----------------------------------------------------------------------------- lazy groups
class LazyGroup(click.Group):
    """A click group whose subcommands are named by ``"module:attr"`` and imported on first use.

    ``lazy`` maps a subcommand name to ``("module:attr", "one-line help")``; the help line is
    what ``--help`` lists, so listing the subcommands imports nothing.  ``attr`` is a click
    command, or a function of no arguments that returns one.  Subcommands added with
    ``@group.command()`` work as usual and are listed after the lazy ones.
    """

    def __init__(self, *args, lazy: dict[str, tuple[str, str]] | None = None, **kwargs):
        kwargs.setdefault("context_settings", CONTEXT_SETTINGS)
        super().__init__(*args, **kwargs)
        self.lazy = dict(lazy or {})

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.lazy) + [n for n in self.commands if n not in self.lazy]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self.commands and cmd_name in self.lazy:
            self.commands[cmd_name] = guard_numbers(load_command(self.lazy[cmd_name][0]))
        return self.commands.get(cmd_name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = []
        for name in self.list_commands(ctx):
            if name in self.lazy:
                rows.append((name, self.lazy[name][1]))
            else:
                cmd = self.commands[name]
                if not cmd.hidden:
                    rows.append(
                        (name, cmd.get_short_help_str(formatter.width - 6 - max(map(len, self.lazy), default=0)))
                    )
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


def load_command(spec: str) -> click.Command:
    """Import ``"module:attr"`` and return its click command (calling ``attr()`` if it is a factory)."""
    module, _, attr = spec.partition(":")
    obj = getattr(importlib.import_module(module), attr)
    if not isinstance(obj, click.Command) and callable(obj):
        obj = obj()
    if not isinstance(obj, click.Command):
        raise TypeError(f"{spec} is not a click command")
    return obj


# ----------------------------------------------------------------------------- errors -> flags
def _flag_of(p: click.Parameter) -> str:
    if isinstance(p, click.Option):
        longs = [o for o in p.opts if o.startswith("--")]
        return (longs or p.opts)[0]
    return p.human_readable_name


def flag_for(command: click.Command | None, name: str) -> str:
    """The flag (or argument) of ``command`` that a library's parameter ``name`` came from.

    Tried in order: the command's :func:`param_flags` rules; a parameter whose Python name
    is ``name`` (dots read as underscores: ``tissue.E`` -> ``tissue_E``); an option spelled
    ``--name``; then the same with the last dotted part only (``inclusion.nu`` -> ``--nu``).
    A name that is already a flag, or that matches nothing, is returned unchanged.
    """
    if command is None or not name or name.startswith("-"):
        return name
    for pattern, flag in getattr(command, "param_flags", {}).items():
        if fnmatch.fnmatchcase(name, pattern):
            return flag
    params = [p for p in command.params if p.name != "help"]
    tries = [name] + ([name.rsplit(".", 1)[1]] if "." in name else [])
    for n in tries:
        key = n.replace(".", "_").replace("-", "_")
        for p in params:
            if p.name == key:
                return _flag_of(p)
        for p in params:
            if isinstance(p, click.Option) and any(o.lstrip("-").replace("-", "_") == key for o in p.opts):
                return _flag_of(p)
    return name


def _leaf_command(command: click.Command, args: list[str], prog_name: str | None) -> click.Command:
    """The (sub)command that ``args`` selects, found by parsing them again without running anything."""
    try:
        ctx = command.make_context(
            prog_name, list(args), resilient_parsing=True, help_option_names=CONTEXT_SETTINGS["help_option_names"]
        )
        while isinstance(ctx.command, click.Group):
            rest = [*getattr(ctx, "_protected_args", []), *ctx.args]
            if not rest:
                break
            name, cmd, rest = ctx.command.resolve_command(ctx, rest)
            if cmd is None:
                break
            ctx = cmd.make_context(name, rest, parent=ctx, resilient_parsing=True)
        return ctx.command
    except Exception:
        return command


def _hint(exc: click.BadParameter) -> str | None:
    if exc.param_hint is not None:
        return exc.param_hint if isinstance(exc.param_hint, str) else " / ".join(exc.param_hint)
    if exc.param is not None:
        return _flag_of(exc.param)
    return None


def run(command: click.Command, args: list[str] | None = None, prog_name: str | None = None) -> None:
    """Run a click command the project's way (see the module docstring); exits the process."""
    argv = sys.argv[1:] if args is None else list(args)
    guard_numbers(command)
    try:
        rv = command.main(
            args=argv,
            prog_name=prog_name,
            standalone_mode=False,
            help_option_names=CONTEXT_SETTINGS["help_option_names"],
        )
    except UserError as exc:
        flag = flag_for(_leaf_command(command, argv, prog_name), exc.param)
        click.echo(f"error: {flag}: {exc.message}", err=True)
        sys.exit(2)
    except click.exceptions.NoSuchOption as exc:
        click.echo(f"error: {exc.format_message()} (see --help)", err=True)
        sys.exit(2)
    except click.exceptions.MissingParameter as exc:
        click.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except click.BadParameter as exc:
        hint = _hint(exc)
        click.echo(f"error: {hint}: {exc.message}" if hint else f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except click.UsageError as exc:
        click.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        click.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)
    if isinstance(rv, int):
        sys.exit(rv)

"""Run a click command so that user mistakes end as one line and exit code 2.

Every console script of the project goes through :func:`run`:

* :class:`elastimap.errors.UserError` and click usage errors print
  ``error: <message>`` on stderr and exit with 2 (no traceback);
* ``KeyboardInterrupt`` exits with 130;
* anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import sys

import click

from .errors import UserError


def run(command: click.Command, args: list[str] | None = None, prog_name: str | None = None) -> None:
    try:
        rv = command.main(args=args, prog_name=prog_name, standalone_mode=False)
    except UserError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except click.exceptions.NoSuchOption as exc:
        click.echo(f"error: {exc.format_message()} (see --help)", err=True)
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

"""User-facing errors.

A :class:`UserError` is a mistake in what the user asked for (a bad parameter,
an unreadable file).  Libraries name the parameter by its Python name
(``jobs``, ``tissue.E``); CLIs print it as one line naming the flag instead
(``error: --jobs: ...``, :func:`elastimap.cli_util.run`) and exit with code 2,
without a traceback; the Python API raises it like any other ``ValueError``.

Checks that raise it (:func:`elastimap.constraints.check_range`, declared rule tables) live in
:mod:`elastimap.constraints`; this module imports nothing of the package.
"""

from __future__ import annotations


class UserError(ValueError):
    """Bad input from the user: ``param`` names what is wrong, ``message`` what is allowed."""

    def __init__(self, param: str, message: str):
        self.param = param
        self.message = message
        super().__init__(f"{param}: {message}")

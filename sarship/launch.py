"""The ``sarship`` console script: a ``sarship detect`` goes to the warm cluster when one runs
(:mod:`sarship.warm`; this module and that path import only the standard library), every other
command (and a detect the warm cluster cannot take) to :func:`sarship.cli.console`."""

from __future__ import annotations

import contextlib
import os
import sys


def console() -> None:
    from sarship import warm

    code = warm.run_remote(sys.argv[1:])
    if code is not None:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)
    from sarship.cli import console as cli_console

    cli_console()

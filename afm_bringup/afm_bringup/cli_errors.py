"""How the `afm` commands refuse damaged or bad input: one line on stderr, exit status 2."""

from __future__ import annotations

import sys

INPUT_STATUS = 2  # the exit status of a refused input (argparse uses it for bad arguments too)


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if text else type(exc).__name__


def refuse(command: str, exc: BaseException) -> int:
    print(f"afm {command}: {one_line(exc)}", file=sys.stderr)
    return INPUT_STATUS

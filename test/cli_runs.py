"""`afm` run in this process, as the command-line tests drive it."""

import contextlib
import io

from afm_bringup.cli import main


def run_cli(argv) -> tuple[int, str]:
    """Exit status and stderr of `afm ARGV`; an exception escapes (a traceback is a failure)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse
            code = exc.code if isinstance(exc.code, int) else 1
    return code, err.getvalue()

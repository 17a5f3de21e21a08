import shlex


class RecordingError(Exception):
    """A recording cannot be written or read; the message names the file and what is wrong."""


def recover_command(path) -> str:
    """The `afm recover` command line a message suggests, the path quoted for a shell (a lab's
    folder names have spaces)."""
    return f"`afm recover {shlex.quote(str(path))}`"

class RecordingError(Exception):
    """A recording cannot be written or read; the message names the file and what is wrong."""

"""The one base class of every user-facing error: the CLI prints these as one line, never a traceback."""


class ElicitError(ValueError):
    """Bad input or an unusable environment, with a message naming the file or field."""

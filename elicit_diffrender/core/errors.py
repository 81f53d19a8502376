"""The one base class of every user-facing error: the CLI prints these as one line, never a traceback."""


class ElicitError(ValueError):
    """Bad input or an unusable environment, with a message naming the file or field."""


def error_line(exc: BaseException) -> str:
    """An error as one line: ``FILE: reason`` for an OS error (a read-only folder, a full disk), else the
    first line of its message."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__

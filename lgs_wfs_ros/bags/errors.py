"""Exceptions of the bag layer: one family, :class:`BagError`, with messages meant for users."""


class BagError(Exception):
    """A bag cannot be read or written; ``str(err)`` says what and where, without a traceback."""


class BagExistsError(BagError, FileExistsError):
    """The output path exists and ``overwrite`` was not given."""


class BagWriteError(BagError, OSError):
    """Writing failed (disk full, file size limit, I/O error); the file was closed at its last
    complete chunk. ``messages_kept`` and ``messages_lost`` count what was and was not saved."""

    def __init__(self, message, messages_kept=0, messages_lost=0):
        super().__init__(message)
        self.messages_kept = messages_kept
        self.messages_lost = messages_lost

    def __str__(self):
        return self.args[0]

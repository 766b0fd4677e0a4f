"""User-facing errors: one clear line, caught by the CLI and printed without a traceback."""


class InputError(ValueError):
    """Bad input data or configuration. The message names the file, line or field and what was expected."""

    def __init__(self, message: str, *, source: str | None = None, line: int | None = None):
        where = ""
        if source is not None:
            where = f"{source}"
            if line is not None:
                where += f", line {line}"
            where += ": "
        super().__init__(where + message)
        self.source = source
        self.line = line

"""User-facing errors: one clear line, caught by the CLI and printed without a traceback."""


class WorkerLost(RuntimeError):
    """A worker process of ours ended without a result (killed from outside, out of memory): not a bug in the input
    nor in the code, so the CLI reports it in one line (exit 1)."""


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


def missing_extra(what: str, package: str, extra: str) -> str:
    """The message for an optional dependency that is not installed: how to add it from PyPI or a checkout."""
    return (f"{what} needs the '{package}' package: pip install {package} "
            f"(or, in a checkout of ti_cmax: pip install -e \".[{extra}]\")")

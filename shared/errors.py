"""The project's one base exception, caught at the edge (CLI, service loops)."""


class AutotuneError(Exception):
    """A user-facing error: its message names the field or thing at fault and why."""


class ConfigError(AutotuneError):
    """Bad settings: a plant file, CLI flags or a Zenoh configuration."""


class DecodeError(AutotuneError):
    """A payload that cannot be accepted: not JSON, wrong schema, wrong types, out of range."""


def printable(text: object) -> str:
    """Text from a file as a table or a line prints it: a character that is not printable (a
    newline, a terminal's escape) written as its escape, so no file breaks the layout or
    drives the terminal (a status of "x\\n\\x1b[31mRED" did both: helper review)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


def one_line(text: object, limit: int = 300) -> str:
    """``text`` on one line (whitespace runs, line breaks included, become one space), cut to
    ``limit`` characters: what a user's own error message becomes inside one of ours."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 1] + "…"

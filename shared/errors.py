"""The project's one base exception, caught at the edge (CLI, service loops)."""


class AutotuneError(Exception):
    """A user-facing error: its message names the field or thing at fault and why."""


class ConfigError(AutotuneError):
    """Bad settings: a plant file, CLI flags or a Zenoh configuration."""


class DecodeError(AutotuneError):
    """A payload that cannot be accepted: not JSON, wrong schema, wrong types, out of range."""

"""Exceptions raised for bad user input.

Every error a user can trigger with a config value or an input file is one of these, carrying one
message that names what is wrong (a config key, a file, a field). The Hydra app catches
:class:`NRCError` and prints the message without a traceback.
"""


class NRCError(Exception):
    """Base class of all user-facing errors of nrc."""


class ConfigError(NRCError, ValueError):
    """A configuration value is missing, malformed or out of range. The message names the key."""


class VDBError(NRCError, ValueError):
    """An OpenVDB file is truncated, corrupted, or uses a feature the reader does not support."""


def failure_line(exc: BaseException) -> str:
    """The first line of an exception's message (at most 200 characters; empty when it has none): a failure of
    torch's machinery (a compile, a graph capture) reported in one line."""
    text = str(exc)
    return text.splitlines()[0][:200] if text else ""

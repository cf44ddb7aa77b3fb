"""The project's error type for input it refuses: a bad argument, file, buffer, channel, config or
checkpoint. Every such error is a `JaxdenoiseError` (and a `ValueError`, as before), with a message
that names what was wrong and what was expected; the CLIs print it as one ``error:`` line. Anything
else that escapes is a bug and keeps its traceback (``jaxdenoise --debug`` shows one for these too).
Imports nothing, so every module can raise it.
"""
from __future__ import annotations

__all__ = ["JaxdenoiseError", "JaxdenoiseWarning", "MissingDependency"]


class JaxdenoiseError(ValueError):
    """Input the library refuses (the message names the argument, file or channel, and why)."""


class MissingDependency(JaxdenoiseError, ImportError):
    """An optional dependency the call needs is not installed (the message names the extra)."""


class JaxdenoiseWarning(UserWarning):
    """A call that runs but not as well as it could: a method without an optional buffer it can use
    (`jaxdenoise.inference.notes`). ``warnings.simplefilter("error", JaxdenoiseWarning)`` makes it fatal."""

"""Error types. Every user-facing error names the file (and field) and how to fix it."""

from __future__ import annotations


class RigbuildError(RuntimeError):
    """Base class for rigbuild errors that a user can act on."""


class InputError(RigbuildError):
    """Bad input: a missing or corrupt file, a malformed config, mismatched data.

    Parameters
    ----------
    message : what is wrong.
    path : the file (or folder) at fault, if any.
    fix : what the user should do about it.
    """

    def __init__(self, message: str, path: str | None = None, fix: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.fix = fix
        text = message
        if path is not None:
            text = f"{path}: {message}"
        if fix:
            text += f"\n  fix: {fix}"
        super().__init__(text)

    def __reduce__(self):  # pickled whole (raised in a worker process, re-raised in the parent)
        return type(self), (self.message, self.path, self.fix)


class QualityGateError(RigbuildError):
    """A stage ran but its result failed a QA gate from the config (e.g. calibration RMS too high)."""

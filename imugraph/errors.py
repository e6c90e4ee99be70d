"""One small exception hierarchy. Messages name the file, the field, what was found and what was expected."""

from __future__ import annotations


class ImugraphError(Exception):
    """Base class: every error imugraph raises on purpose. The CLI prints it as one line."""


class SessionError(ImugraphError):
    """A session file or its contents are unusable."""

    def __init__(self, source: str, field: str, found: str, expected: str):
        self.source, self.field, self.found, self.expected = source, field, found, expected
        super().__init__(f"{source}: field '{field}': found {found}; expected {expected}")


class CalibrationError(ImugraphError):
    """The data do not allow a calibration (ill-conditioned fit, too little rotation, ...)."""

"""Errors of the calibration package; all are `RigdError`s so the CLI reports them uniformly."""

from __future__ import annotations

from rigd.core.errors import RigdError


class CalibrationError(RigdError):
    """Calibration could not be done; the message names the view, file or camera at fault."""


class BoardSpecError(CalibrationError):
    """A board spec string is malformed; the message quotes it and gives the grammar."""


class NoBoardFoundError(CalibrationError):
    """No image of a set showed the board, so there is nothing to calibrate from."""

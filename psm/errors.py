"""Errors raised by the PSM core. Every invalid input raises a :class:`PSMError` subclass whose
message names the problem (field, shape, index), so callers can show one clear line."""


class PSMError(Exception):
    """Base class of every error the PSM core raises on purpose."""


class DemonstrationError(PSMError, ValueError):
    """The demonstration cannot be learned from: NaN/inf, too few samples, bad time stamps."""


class ShapeError(PSMError, ValueError):
    """An array has the wrong shape or dimension count (e.g. a goal of the wrong length)."""


class ModelFileError(PSMError, ValueError):
    """A saved model cannot be read: not JSON, wrong schema, unsupported version."""


class ParameterError(PSMError, ValueError):
    """A parameter is out of its valid range (e.g. negative smoothing, dt <= 0)."""

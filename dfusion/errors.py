"""The exceptions dfusion raises.

Every exception derives from :class:`DfusionError`; the ones about bad input
also derive from :class:`ValueError`, so ``except ValueError`` keeps working.
Whenever a public method raises one of these, the object it was called on is
left exactly as it was before the call.

::

    DfusionError
    ├── ValidationError (ValueError)        bad numbers or shapes
    │   ├── ShapeError                      wrong shape or dimension
    │   ├── NonFiniteError                  NaN or inf
    │   └── NotPositiveDefiniteError        a covariance/information matrix that is not PD
    ├── TimeError (ValueError)              a time stamp the filter cannot use
    │   └── OutsideWindowError              older than the window, or ahead of the newest state
    ├── NotInitializedError (RuntimeError)  a filter used before ``initialize``
    ├── MessageError (ValueError)           a malformed or misaddressed fusion message
    ├── TopologyError (ValueError)          a communication graph that is not a tree
    └── ScenarioError (ValueError)          an invalid scenario file
"""
from __future__ import annotations


class DfusionError(Exception):
    """Base class of every error raised by dfusion."""


class ValidationError(DfusionError, ValueError):
    """An input array has the wrong shape, non-finite entries or is not positive definite."""


class ShapeError(ValidationError):
    """An array does not have the shape the model or filter expects."""


class NonFiniteError(ValidationError):
    """An array contains NaN or infinity."""


class NotPositiveDefiniteError(ValidationError):
    """A matrix that must be symmetric positive definite is not."""


class TimeError(DfusionError, ValueError):
    """A time stamp cannot be used (for example it is not increasing)."""


class OutsideWindowError(TimeError):
    """A time stamp lies before the oldest state kept in the window, or after the newest."""


class NotInitializedError(DfusionError, RuntimeError):
    """The filter was used before ``initialize`` was called."""


class MessageError(DfusionError, ValueError):
    """A fusion message is malformed, from a non-neighbour, or addressed to another node."""


class TopologyError(DfusionError, ValueError):
    """A communication graph is not a connected tree."""


class ScenarioError(DfusionError, ValueError):
    """A scenario file is invalid."""

"""The exceptions jaxsync raises for bad input.

Everything jaxsync raises on purpose is a ``JaxsyncError``; the CLI turns
these into a one-line message and a non-zero exit.
"""


class JaxsyncError(Exception):
    """Base class of every error jaxsync raises on purpose.

    The message speaks in the library's words: the Python parameters by
    name. ``inputs`` names the parameters it is about, so that a front end
    can say which of its own options they are (the command line appends its
    flags: ``jaxsync.cli``)."""

    def __init__(self, message: str = "", *, inputs: tuple[str, ...] = ()):
        super().__init__(message)
        self.inputs = tuple(inputs)


class ModelError(JaxsyncError):
    """An MJCF model that cannot be used."""


class ModelFileError(ModelError):
    """The MJCF file is missing, unreadable or does not compile."""


class ModelStructureError(ModelError):
    """The model compiles but lacks names that jaxsync needs."""


class ConfigError(JaxsyncError):
    """A gain, scenario or option value outside what is allowed."""


class DroppedObjectError(JaxsyncError):
    """Gains that drop the object wherever they are tried: nothing to measure or tune."""


class UntrustedResultError(JaxsyncError):
    """A result the inputs do not support (a calibration its recording does not determine): refused, not given."""

"""The error tree of the core library.

Every error a user can cause derives from :class:`PanoGSError`. Messages name the argument or file, what was
expected and what arrived, so that the service can show them unchanged.
"""

from __future__ import annotations


class PanoGSError(Exception):
    """Base of every error raised on purpose by ``panogs_core``."""


class InputError(PanoGSError, ValueError):
    """An input (array, file, argument) does not meet the contract."""


class ShapeError(InputError):
    """An array has the wrong shape or dtype."""


class BundleError(InputError):
    """A scene bundle breaks ``docs/scene_format.md``; carries every problem found, not just the first.

    Attributes:
        problems: One line per problem, each naming the file, the field and the value found.
    """

    def __init__(self, problems: list[str], source: str = "bundle") -> None:
        self.problems = list(problems)
        self.source = source
        head = f"{source}: {len(self.problems)} problem(s)"
        super().__init__(head + "".join(f"\n  - {p}" for p in self.problems))


class ConfigError(PanoGSError, ValueError):
    """A configuration value is out of range, or a config file has an unknown key."""


class EncoderUnavailableError(PanoGSError):
    """No text encoder can embed queries for this feature space on this machine."""


class NumericalError(PanoGSError):
    """A computation produced NaN or infinite values that cannot be recovered."""


class Cancelled(PanoGSError):
    """Raised (usually by a progress callback) to stop a pipeline run cooperatively.

    A long stage that keeps snapshots of its partial work (the appearance fit,
    :mod:`panogs_core.snapshots`) writes one before it lets the exception through, so that a resumed run
    continues where this one stopped; a subclass whose run must write nothing more (another worker now owns the
    job's folder) sets ``save_partial_work`` False.
    """

    save_partial_work: bool = True

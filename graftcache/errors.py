"""Exception types. Every user-facing failure names the file, episode, frame or key it concerns."""


class GraftcacheError(Exception):
    """Base class: the CLI prints these as one line and exits non-zero (no traceback)."""


class DatasetError(GraftcacheError):
    """A dataset on disk is missing, malformed or inconsistent with its metadata."""


class EncoderError(GraftcacheError):
    """An encoder name, weights file or configuration cannot be resolved."""


class CacheError(GraftcacheError):
    """A feature cache is missing, incomplete, locked, stale or does not match the request."""


class NumericsError(CacheError):
    """This environment computes different features than the one that made a cache (its numerics fingerprint)."""


class BackboneError(GraftcacheError):
    """A policy checkpoint or backbone configuration cannot be loaded or grafted."""


class FitError(GraftcacheError):
    """A fit request is inconsistent with the cache it names (width, dataset, suite, controls)."""


class ExecutorError(GraftcacheError):
    """A distributed executor cannot do the work: no cluster at the address, a task the cluster cannot place,
    a task lost more often than it may be retried."""


class ResultsError(GraftcacheError):
    """A results file cannot be read or written: not Parquet, a directory, a read-only place, a value its
    column cannot hold without changing it."""


class ExportError(GraftcacheError):
    """A cell that cannot be exported as a policy, or an export folder that cannot be run here."""


class RolloutError(GraftcacheError):
    """A cell that cannot be rolled out in the simulator (none installed, cameras it cannot feed, a shuffled-image
    control), or a rollouts file that cannot be read or written."""


class Deprecation(FutureWarning):
    """A former flag or recipe key that still reads (graftcache.settings.Setting.formerly): the CLI prints it as one
    line naming the new spelling (graftcache.cli.main), not as a warning located in argparse or the TOML reader."""


def first_line(error: BaseException) -> str:
    """The first line of an exception's message, else its type's name: what a one-line message quotes of an error a
    library raised (polars, the OS, Ray and safetensors often append pages of detail)."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__

"""One error for a take whose contents break the format: `TakeFormatError`, naming the file.

The structural check (rigd/take/structure.py) refuses what HDF5 must never be asked to follow;
what is left is metadata a reader parses (attributes, index rows, JSON) and may find wrong in
ways no list of checks anticipates: an attribute of the wrong type, a count that overflows, a
JSON document nested past the interpreter's recursion limit. The reader's public methods run
under `format_errors`, so any such failure reaches the caller as one TakeFormatError (the
original chained as its cause), never as the IndexError of whichever line met it first.

`OpenTake` is what a series needs of its take (path, status, time domain): the Take hands it
to each FrameSeries and EventSeries it gives out, so no series reaches into the Take.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from rigd.core.errors import EventDataError, TakeError, TakeFormatError
from rigd.core.layout import TimeDomain

#: What reading damaged metadata raises (h5py: OSError/RuntimeError for unreadable data).
DAMAGE_ERRORS: tuple[type[BaseException], ...] = (
    OSError,
    RuntimeError,
    KeyError,
    IndexError,
    ValueError,
    TypeError,
    OverflowError,
    ZeroDivisionError,
    AttributeError,
    EventDataError,
)

C = TypeVar("C", bound=type)
#: Special methods that read the take (`len(series)`, `series[i]`).
_DUNDERS = frozenset({"__getitem__", "__len__"})


class OutOfRangeError(IndexError):
    """An index the caller asked for is past the end (not damage): passes the guard as it is,
    and ends iteration over a Sequence as IndexError must."""


def as_format_error(where: str | Path, what: str, exc: BaseException) -> TakeFormatError:
    """`exc` met while reading `what` of the take at `where`, as one TakeFormatError."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    detail = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return TakeFormatError(f"{where}: damaged: {what} cannot be read ({detail})")


def _wrap(fn: Callable[..., Any], what: str) -> Callable[..., Any]:
    @functools.wraps(fn)
    def guarded(self: Any, *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(self, *args, **kwargs)
        except (TakeError, OutOfRangeError):
            raise
        except RecursionError as exc:
            raise as_format_error(self._where_file(), what, exc) from None
        except DAMAGE_ERRORS as exc:
            raise as_format_error(self._where_file(), what, exc) from exc

    return guarded


def format_errors(cls: C) -> C:
    """Class decorator: every public method and property of `cls` raises TakeFormatError for
    damaged contents; `cls` provides `_where_file()` (the file and object it reads)."""
    for name, member in list(vars(cls).items()):
        if name.startswith("_") and name not in _DUNDERS:
            continue
        what = f"{cls.__name__}.{name}"
        if isinstance(member, property) and member.fget is not None:
            setattr(cls, name, property(_wrap(member.fget, what), member.fset, member.fdel, member.__doc__))
        elif inspect.isfunction(member) and not inspect.isgeneratorfunction(member):
            setattr(cls, name, _wrap(member, what))
    return cls


@dataclass(frozen=True, slots=True)
class OpenTake:
    """What a series reads of its open take: the file, its status and its time domain (fixed
    while the take is open read-only)."""

    path: Path
    status: str
    time_domain: str

    def require_rig(self, where: str) -> None:
        """Refuse a time query on a take never finalized (its times are in each device's clock)."""
        if self.time_domain != TimeDomain.RIG:
            raise TakeError(
                f"{self.path}: {where}: time queries need rig time, but this take was never finalized "
                f"(status {self.status!r}, times are still in each device's own clock)"
            )

"""A numba cache the running user can write, chosen before numba is imported.

The event decoders are compiled with `cache=True`; numba then needs a writable place for the
cache (beside the source, under ~/.cache, or NUMBA_CACHE_DIR) and raises at the first decode
when it finds none, which is what a user running an installed rigd from a read-only tree with
no home gets (a traceback in the middle of `rigd capture`). When no such place exists this
points NUMBA_CACHE_DIR at one the user owns.
"""

from __future__ import annotations

import logging
import os
import stat
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

ENV = "NUMBA_CACHE_DIR"


def _writable_dir(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)


def _own_dir(path: Path) -> bool:
    """A directory this user created or owns, private to it (not one another user prepared)."""
    if not _writable_dir(path):
        return False
    st = path.lstat()
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid()


def _source_writable() -> bool:
    import drivers

    return os.access(Path(drivers.__file__).parent, os.W_OK)


def _home_cache() -> Path | None:
    home = os.environ.get("HOME")
    return Path(os.environ.get("XDG_CACHE_HOME") or f"{home}/.cache") if home else None


def ensure_numba_cache() -> str | None:
    """Set NUMBA_CACHE_DIR when numba would find nowhere to write its cache; returns the
    directory set, or None when the environment already works."""
    given = os.environ.get(ENV)
    if given:
        if _writable_dir(Path(given)):
            return None
        log.warning("%s=%s is not writable by this user; using a private cache instead", ENV, given)
    elif _source_writable():
        return None
    else:
        home = _home_cache()
        if home is not None and _writable_dir(home):
            return None  # numba's user-wide cache under ~/.cache
    candidates = [Path(tempfile.gettempdir()) / f"rigd-numba-{os.getuid()}"]
    home = _home_cache()
    if home is not None:
        candidates.insert(0, home / "rigd" / "numba")
    for path in candidates:
        if _own_dir(path):
            os.environ[ENV] = str(path)
            return str(path)
    log.warning(
        "no writable directory for numba's cache (tried %s): set %s", ", ".join(map(str, candidates)), ENV
    )
    return None

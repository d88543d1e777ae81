"""Where a reconstruction runs: the same Dask graph on local threads (default), local processes,
the synchronous scheduler, or a `dask.distributed` cluster (`scheduler="tcp://host:8786"`). Dask is
imported only when a runner is made, with a message naming what to install.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Any

from rigd.core.errors import ConfigError, RigdError

LOCAL_SCHEDULERS = ("threads", "processes", "sync")
#: A dask.distributed address: PROTOCOL://HOST:PORT (HOST a name, IPv4 or [IPv6]), HOST:PORT
#: (tcp), or an in-process scheduler's inproc://... address.
_ADDRESS = re.compile(
    r"((?:tcp|tls|ucx|ws|wss)://)?(?P<host>[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?|\[[0-9A-Fa-f:.]+\])"
    r":(?P<port>[0-9]{1,5})|inproc://\S+"
)
SCHEDULER_FORMS = f"{', '.join(LOCAL_SCHEDULERS)}, or a dask.distributed address tcp://HOST:PORT"


def check_scheduler(v: str | None) -> str | None:
    """`v` when it names a local scheduler or is a well-formed distributed address (port
    1-65535); else ValueError saying which forms are accepted."""
    if v is None or v in LOCAL_SCHEDULERS:
        return v
    m = _ADDRESS.fullmatch(v)
    if m is None or (m["port"] is not None and not 1 <= int(m["port"]) <= 65535):
        shown = repr(v if len(v) <= 60 else v[:57] + "...")
        raise ValueError(f"{shown}: expected {SCHEDULER_FORMS} (port 1-65535)")
    return v


#: Seconds to wait for a distributed scheduler to answer (dask's default is 30).
CONNECT_TIMEOUT_S = 5


class DaskRunner:
    """Computes lists of Dask tasks on one scheduler, calling `on_result` per finished task."""

    def __init__(self, scheduler: str | None, workers: int | None) -> None:
        try:
            import dask  # noqa: F401
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise RigdError(
                "rigd reconstruct needs dask: pip install dask (distributed for --scheduler)"
            ) from exc
        self.name = scheduler or "threads"
        self.workers = workers
        self._client: Any = None
        if self.name not in LOCAL_SCHEDULERS:
            try:
                from dask.distributed import Client
            except ImportError as exc:  # pragma: no cover - depends on the environment
                raise RigdError(
                    f"--scheduler {self.name}: a distributed scheduler needs dask.distributed "
                    "(pip install distributed)"
                ) from exc
            try:
                self._client = Client(self.name, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError) as exc:
                raise ConfigError(
                    f"--scheduler {self.name}: no dask.distributed scheduler answered within "
                    f"{CONNECT_TIMEOUT_S} s ({' '.join(str(exc).split())}); start one with "
                    f"`dask scheduler` or use {', '.join(LOCAL_SCHEDULERS)}"
                ) from exc
            except ValueError as exc:  # an address dask cannot parse
                raise ConfigError(
                    f"--scheduler {self.name}: not a usable dask.distributed address "
                    f"({' '.join(str(exc).split())}); expected {SCHEDULER_FORMS}"
                ) from exc

    def close(self) -> None:
        if self._client is not None:
            self._client.close()

    def compute(self, tasks: Sequence[Any], on_result: Callable[[Any], None]) -> list[Any]:
        if not tasks:
            return []
        if self._client is not None:
            from dask.distributed import as_completed

            futures = self._client.compute(list(tasks))
            for fut in as_completed(futures):
                on_result(fut.result())
            return [f.result() for f in futures]
        import dask
        from dask.callbacks import Callback

        def posttask(key: Any, result: Any, dsk: Any, state: Any, worker_id: Any) -> None:
            on_result(result)

        kwargs: dict[str, Any] = {"scheduler": self.name}
        if self.workers is not None and self.name != "sync":
            kwargs["num_workers"] = self.workers
        with Callback(posttask=posttask):
            return list(dask.compute(*tasks, **kwargs))

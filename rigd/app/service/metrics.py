"""Prometheus metrics for `rigd serve`, mapped from the daemon's `Telemetry` snapshots.

The exporter owns a private CollectorRegistry (not prometheus_client's global one), so two
exporters in one process (tests) never collide and nothing else leaks into the scrape.

Counters and takes: Telemetry's `pulses`, `bytes_written` and per-device `total`/`lost` count
from zero in every take. Prometheus counters must only go up (a drop reads as a process
restart to `rate()`/`increase()`), and a gauge of per-take numbers cannot be summed over time.
So each `..._total` here is a daemon-lifetime counter fed with the *increase* between
consecutive snapshots: a snapshot of a new take starts from a zero baseline; a value lower than
the last one seen (numbers reset without a new take name) counts from zero too. What a take
wrote after its last snapshot is topped up from its `TakeSummary` (frames, events, bytes), so
`increase()` over a take matches the take file; pulses have no summary and may miss the last
interval's.

Times are in seconds (Prometheus base unit), also for microsecond-scale sync numbers: Grafana
shows 2e-06 s as 2 µs.

Thread safety: `update()` runs on the daemon's thread while the HTTP thread scrapes; each
metric is thread-safe, a scrape may see a snapshot half applied (harmless for monitoring).

Who may scrape (docs/security.md): on loopback, any local user, unless a bearer token is
configured (`service.metrics_token_file`), which then every scrape needs. Beyond loopback the
token is required: the exporter refuses to start without one, as the control socket refuses a
non-private bind without CurveZMQ keys.
"""

from __future__ import annotations

import contextlib
import errno
import hmac
import logging
import socket
import stat
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, Counter, Gauge, Info, ProcessCollector, make_wsgi_app
from prometheus_client.core import CounterMetricFamily, Metric
from prometheus_client.exposition import ThreadingWSGIServer
from prometheus_client.registry import Collector

from rigd import __version__
from rigd.app.service import sdnotify
from rigd.app.service.hosts import is_loopback
from rigd.app.service.protocol import DaemonState, DeviceTelemetry, Fault, TakeSummary, Telemetry
from rigd.core.errors import ConfigError

if TYPE_CHECKING:
    from wsgiref.types import StartResponse, WSGIApplication, WSGIEnvironment

log = logging.getLogger(__name__)

#: What `--metrics-port` takes besides a port, as the errors say it.
PORT_CHOICES = "0: any free port, -1: off"

DAEMON_STATES: tuple[str, ...] = get_args(DaemonState)
DEVICE_STATES: tuple[str, ...] = get_args(DeviceTelemetry.model_fields["state"].annotation)
FAULT_CODES: tuple[str, ...] = get_args(Fault.model_fields["code"].annotation)

DEFAULT_PORT = 9464  # the port OpenTelemetry's Prometheus exporter uses by convention


class _SdNotifyCollector(Collector):
    """Exposes sd_notify send failures (counted by `sdnotify`, which must not depend on us)."""

    def collect(self) -> Iterable[Metric]:
        family = CounterMetricFamily(
            "rigd_sdnotify_failures", "systemd notifications that could not be sent."
        )
        family.add_metric([], sdnotify.failures())
        yield family


class _Deltas:
    """Turns snapshot values that may reset into increases for a monotonic counter."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, ...], float] = {}

    def increase(self, key: tuple[str, ...], value: float) -> float:
        last = self._last.get(key, 0.0)
        self._last[key] = value
        return value - last if value >= last else value

    def top_up(self, key: tuple[str, ...], value: float) -> float:
        """Increase up to a final `value` (a take's summary); never a reset."""
        last = self._last.get(key, 0.0)
        if value <= last:
            return 0.0
        self._last[key] = value
        return value - last

    def reset(self) -> None:
        self._last.clear()


#: Bearer tokens shorter than this are refused (guessable).
MIN_TOKEN_CHARS = 16


def read_token_file(path: Path) -> str:
    """The bearer token in `path` (surrounding whitespace dropped); ConfigError naming the key when
    it cannot be read, is readable by group or others (a secret), or is too short."""
    where = f"service.metrics_token_file: {path}"
    try:
        mode = path.stat().st_mode
        text = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ConfigError(f"{where}: cannot read it: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{where}: not a text file") from exc
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(f"{where}: readable by group or others (mode {stat.S_IMODE(mode):o}); chmod 600 it")
    if len(text) < MIN_TOKEN_CHARS:
        raise ConfigError(f"{where}: the token must have at least {MIN_TOKEN_CHARS} characters")
    return text


def bearer_only(app: WSGIApplication, token: str) -> WSGIApplication:
    """`app` behind `Authorization: Bearer <token>` (compared in constant time); 401 otherwise."""
    expected = f"Bearer {token}".encode()

    def guarded(environ: WSGIEnvironment, start_response: StartResponse) -> Iterable[bytes]:
        got = str(environ.get("HTTP_AUTHORIZATION", "")).encode()
        if hmac.compare_digest(got, expected):
            return app(environ, start_response)
        body = b"rigd metrics need the bearer token of service.metrics_token_file\n"
        start_response(
            "401 Unauthorized",
            [
                ("Content-Type", "text/plain; charset=utf-8"),
                ("Content-Length", str(len(body))),
                ("WWW-Authenticate", 'Bearer realm="rigd metrics"'),
            ],
        )
        return [body]

    return guarded


class _QuietHandler(WSGIRequestHandler):
    """No access log on stderr (scrapes every few seconds)."""

    def log_message(self, format: str, *args: Any) -> None:
        """Scrapes are not logged."""


class MetricsExporter:
    """Serves rigd's metrics on http://HOST:PORT/metrics from the last `update()`."""

    def __init__(
        self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, token_file: Path | None = None
    ) -> None:
        """ConfigError, before anything binds, for a non-loopback host without a token file (or a
        token file that is unreadable, open to others or too short)."""
        if token_file is None and not is_loopback(host):
            raise ConfigError(
                f"service.metrics_host: {host} would serve metrics beyond loopback without "
                "authentication; set service.metrics_token_file (a bearer token) or a loopback address"
            )
        self._token = read_token_file(token_file) if token_file is not None else None
        self._host = host
        self._port = port
        self._server: WSGIServer | None = None
        self._thread: threading.Thread | None = None
        # Per-take values reset when the take changes; daemon-lifetime values never do.
        self._take: str | None = None
        self._last_take_path: str | None = None
        self._updates = 0
        self._take_deltas = _Deltas()
        self._lifetime_deltas = _Deltas()
        self._devices: set[str] = set()
        self._device_kinds: dict[str, str] = {}
        self._last_take_devices: set[str] = set()

        r = self.registry = CollectorRegistry(auto_describe=True)
        Info("rigd_build", "rigd version.", registry=r).info({"version": __version__})
        ProcessCollector(registry=r)  # process_* (CPU, RSS, open fds, start time), Linux only
        r.register(_SdNotifyCollector())

        # Declared in the order /metrics lists them.
        self._declare_daemon_series(r)
        self._declare_device_series(r)
        self._declare_writer_series(r)
        self._declare_outcome_series(r)

        # Series that exist before the first snapshot, so alerts and dashboards see zeros.
        for s in DAEMON_STATES:
            self.state.labels(state=s).set(0)
        for c in FAULT_CODES:
            self.faults.labels(code=c).set(0)

    def _declare_daemon_series(self, r: CollectorRegistry) -> None:
        """The daemon's state and the running take's progress."""
        self.up = Gauge("rigd_up", "1 while the daemon serves.", registry=r)
        self.state = Gauge(
            "rigd_state", "1 for the daemon's current state, 0 otherwise.", ["state"], registry=r
        )
        self.telemetry_time = Gauge(
            "rigd_telemetry_last_update_timestamp_seconds",
            "Unix time of the last telemetry snapshot (stale = daemon loop stuck).",
            registry=r,
        )
        self.take_active = Gauge("rigd_take_active", "1 while a take is running.", registry=r)
        self.take_elapsed = Gauge("rigd_take_elapsed_seconds", "Age of the running take.", registry=r)
        self.pulses = Counter("rigd_pulses_total", "Trigger pulses recorded, all takes.", registry=r)

    def _declare_device_series(self, r: CollectorRegistry) -> None:
        """Per device: what it delivered and lost, its state, its clock's health."""
        self.device_items = Counter(
            "rigd_device_items_total",
            "Frames, events or pulse records written, all takes.",
            ["device", "kind"],
            registry=r,
        )
        self.device_lost = Counter(
            "rigd_device_lost_total", "Items recorded as lost, all takes.", ["device", "kind"], registry=r
        )
        self.device_reconnects = Counter(
            "rigd_device_reconnects_total", "Device reconnections.", ["device"], registry=r
        )
        self.device_rate = Gauge(
            "rigd_device_items_per_second",
            "Frames, events or pulses per second over the last telemetry interval.",
            ["device", "kind"],
            registry=r,
        )
        self.device_up = Gauge("rigd_device_up", "1 when the device's state is ok.", ["device"], registry=r)
        self.device_state = Gauge(
            "rigd_device_state",
            "1 for the device's current state, 0 otherwise.",
            ["device", "state"],
            registry=r,
        )
        self.device_data_age = Gauge(
            "rigd_device_last_data_age_seconds",
            "Time since the device last delivered.",
            ["device"],
            registry=r,
        )
        self.device_jitter = Gauge(
            "rigd_device_interval_jitter_seconds",
            "Std of the device-clock trigger intervals minus the trigger period (live sync health).",
            ["device"],
            registry=r,
        )

    def _declare_writer_series(self, r: CollectorRegistry) -> None:
        """The queue, the writer thread and the disk the takes go to."""
        self.queue_depth = Gauge("rigd_queue_depth", "Items in the acquisition->writer queue.", registry=r)
        self.queue_bytes = Gauge(
            "rigd_queue_bytes", "Bytes held by the acquisition->writer queue.", registry=r
        )
        self.writer_busy = Gauge(
            "rigd_writer_busy_ratio", "Share of the last seconds the writer thread was busy.", registry=r
        )
        self.queue_capacity = Gauge(
            "rigd_queue_capacity", "Bound of the acquisition->writer queue.", registry=r
        )
        self.written_bytes = Counter(
            "rigd_written_bytes_total", "Bytes written to takes, all takes.", registry=r
        )
        self.write_rate = Gauge(
            "rigd_write_rate_bytes_per_second", "Take write rate over the last interval.", registry=r
        )
        self.flush_age = Gauge(
            "rigd_take_last_flush_age_seconds",
            "Seconds since the running take was last flushed: what a crash now would lose.",
            registry=r,
        )
        self.flush_max = Gauge(
            "rigd_take_flush_max_seconds", "The running take's longest flush (writer stall).", registry=r
        )
        self.disk_free = Gauge("rigd_disk_free_bytes", "Free bytes on the take directory's disk.", registry=r)
        self.disk_total = Gauge("rigd_disk_total_bytes", "Size of the take directory's disk.", registry=r)

    def _declare_outcome_series(self, r: CollectorRegistry) -> None:
        """Active faults and how the finished takes ended."""
        self.faults = Gauge("rigd_faults", "Active faults by code.", ["code"], registry=r)
        self.takes_completed = Counter("rigd_takes_completed_total", "Takes finalized.", registry=r)
        self.last_take_residual = Gauge(
            "rigd_last_take_residual_rms_seconds",
            "Sync residual RMS per device in the last finalized take.",
            ["device"],
            registry=r,
        )
        self.last_take_bytes = Gauge("rigd_last_take_bytes", "Bytes written by the last take.", registry=r)
        self.last_take_failed = Gauge(
            "rigd_last_take_failed", "1 when the last take ended with an error.", registry=r
        )

    # -- lifecycle -------------------------------------------------------------------------

    @property
    def port(self) -> int:
        """The bound port once started (the real one for port 0), else the configured one."""
        if self._server is not None:
            return int(self._server.server_address[1])
        return self._port

    @property
    def url(self) -> str:
        host = f"[{self._host}]" if ":" in self._host else self._host
        return f"http://{host}:{self.port}/metrics"

    def start(self) -> None:
        """Bind and serve on a daemon thread.

        A port that cannot be bound is a ConfigError like the daemon's other endpoints, so
        `rigd serve` exits with its config status instead of a traceback (and systemd does not
        restart it into the same taken port).
        """
        if self._server is not None:
            raise RuntimeError("metrics exporter already started")
        app = make_wsgi_app(self.registry)
        if self._token is not None:
            app = bearer_only(app, self._token)
        try:
            family = socket.getaddrinfo(self._host.strip("[]"), self._port, type=socket.SOCK_STREAM)[0][0]

            class _Server(ThreadingWSGIServer):
                address_family = family

            # Our own server (not start_http_server): the app may sit behind the bearer check,
            # and we keep the server to read the bound port and to free it in close().
            server = make_server(
                self._host.strip("[]"), self._port, app, _Server, handler_class=_QuietHandler
            )
        except OSError as exc:
            raise ConfigError(
                f"cannot serve metrics on {self._host}:{self._port}: {exc.strerror or exc}"
                + (" (another rigd daemon on this host?)" if exc.errno == errno.EADDRINUSE else "")
                + f"; give this daemon another port: `rigd serve --metrics-port PORT` ({PORT_CHOICES}) "
                "or service.metrics_port in the rig config"
            ) from exc
        self._server = server
        self._thread = threading.Thread(target=server.serve_forever, name="metrics-http", daemon=True)
        self._thread.start()
        self.up.set(1)
        log.info("metrics on %s%s", self.url, " (bearer token required)" if self._token else "")

    def close(self) -> None:
        """Stop serving and free the port; idempotent."""
        server, thread = self._server, self._thread
        if server is None:
            return
        port = self.port
        self.up.set(0)
        server.shutdown()
        server.server_close()
        if thread is not None:
            thread.join(timeout=5)
            if thread.is_alive():
                log.warning("metrics server thread did not stop within 5 s")
        self._server = self._thread = None
        log.debug("metrics server on port %d closed", port)

    def __enter__(self) -> MetricsExporter:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- telemetry -------------------------------------------------------------------------

    def update(self, t: Telemetry) -> None:
        """Map one telemetry snapshot onto the metrics."""
        self._updates += 1
        self.telemetry_time.set(time.time())
        for s in DAEMON_STATES:
            self.state.labels(state=s).set(1 if s == t.state else 0)

        # Before the per-take numbers: the snapshot that brings a take's summary already shows
        # the next (idle) numbers, and the summary holds what happened after the last snapshot.
        self._account_finished_take(t.last_take)
        if t.take is not None and t.take != self._take:
            # A new take: its numbers start from zero, so must the baselines. A snapshot
            # without a take (idle) keeps the baselines: it may still show the last take's
            # final numbers, which must not be counted twice.
            self._take = t.take
            self._take_deltas.reset()
        self.take_active.set(1 if t.take is not None else 0)
        self.take_elapsed.set(t.take_elapsed_s if t.take is not None else 0.0)

        take, life = self._take_deltas, self._lifetime_deltas
        self._inc(self.pulses, take.increase(("pulses",), t.pulses))
        self._inc(self.written_bytes, take.increase(("bytes",), t.bytes_written))
        self._inc(self.takes_completed, life.increase(("takes",), t.takes_completed))

        self.queue_depth.set(t.queue_depth)
        self.queue_bytes.set(t.queue_bytes)
        self.writer_busy.set(t.writer_busy)
        self.queue_capacity.set(t.queue_capacity)
        self.write_rate.set(t.write_rate_bytes_s)
        self.flush_age.set(t.last_flush_age_s if t.last_flush_age_s is not None else 0.0)
        self.flush_max.set(t.flush_max_s)
        self.disk_free.set(t.disk_free_bytes)
        self.disk_total.set(t.disk_total_bytes)

        self._update_devices(t.devices)

        counts = dict.fromkeys(FAULT_CODES, 0)
        for fault in t.faults:
            counts[fault.code] = counts.get(fault.code, 0) + 1
        for code, n in counts.items():
            self.faults.labels(code=code).set(n)

        self._update_last_take(t)

    def _update_devices(self, devices: list[DeviceTelemetry]) -> None:
        take, life = self._take_deltas, self._lifetime_deltas
        seen: set[str] = set()
        for d in devices:
            seen.add(d.name)
            self._device_kinds[d.name] = d.kind
            self._inc(
                self.device_items.labels(device=d.name, kind=d.kind),
                take.increase(("items", d.name), d.total),
            )
            self._inc(
                self.device_lost.labels(device=d.name, kind=d.kind), take.increase(("lost", d.name), d.lost)
            )
            # Reconnects may be counted per take or per daemon; the lifetime rule is right for
            # both (a drop is a reset) and never counts one twice.
            self._inc(
                self.device_reconnects.labels(device=d.name),
                life.increase(("reconnects", d.name), d.reconnects),
            )
            self.device_rate.labels(device=d.name, kind=d.kind).set(d.rate_hz)
            self.device_up.labels(device=d.name).set(1 if d.state == "ok" else 0)
            for s in DEVICE_STATES:
                self.device_state.labels(device=d.name, state=s).set(1 if s == d.state else 0)
            self._set_or_remove(self.device_data_age, d.name, d.last_data_age_s)
            jitter = None if d.interval_jitter_us is None else d.interval_jitter_us * 1e-6
            self._set_or_remove(self.device_jitter, d.name, jitter)
        # A device gone from the config must not keep reporting "up"; its counters stay.
        for name in self._devices - seen:
            kind = self._device_kinds.pop(name, "")
            self._remove(self.device_rate, name, kind)
            self._remove(self.device_up, name)
            for s in DEVICE_STATES:
                self._remove(self.device_state, name, s)
            self._remove(self.device_data_age, name)
            self._remove(self.device_jitter, name)
        self._devices = seen

    def _account_finished_take(self, last: TakeSummary | None) -> None:
        """Count the frames, events and bytes a take wrote after the last snapshot of it."""
        if last is None or last.path == self._last_take_path:
            return
        self._last_take_path = last.path
        if self._updates == 1:
            return  # a take that ended before this exporter saw anything is not ours to count
        if last.path != self._take:
            # It began and ended between two snapshots: nothing of it is counted yet.
            self._take = last.path
            self._take_deltas.reset()
        take = self._take_deltas
        for kind, items in (("rgb_camera", last.frames), ("event_sensor", last.events)):
            for name, n in items.items():
                self._inc(self.device_items.labels(device=name, kind=kind), take.top_up(("items", name), n))
        self._inc(self.written_bytes, take.top_up(("bytes",), last.bytes_written))

    def _update_last_take(self, t: Telemetry) -> None:
        last = t.last_take
        if last is None:
            return
        for name in self._last_take_devices - set(last.residual_rms_us):
            self._remove(self.last_take_residual, name)
        for name, rms_us in last.residual_rms_us.items():
            self.last_take_residual.labels(device=name).set(rms_us * 1e-6)
        self._last_take_devices = set(last.residual_rms_us)
        self.last_take_bytes.set(last.bytes_written)
        self.last_take_failed.set(1 if last.error is not None or last.status == "failed" else 0)

    @staticmethod
    def _inc(counter: Counter, amount: float) -> None:
        if amount > 0:
            counter.inc(amount)

    @staticmethod
    def _set_or_remove(gauge: Gauge, device: str, value: float | None) -> None:
        """Absent rather than NaN when the daemon has no value (Prometheus convention)."""
        if value is None:
            MetricsExporter._remove(gauge, device)
        else:
            gauge.labels(device=device).set(value)

    @staticmethod
    def _remove(gauge: Gauge, *labels: str) -> None:
        # Older prometheus_client versions raise KeyError for a label set never set: nothing to do.
        with contextlib.suppress(KeyError):
            gauge.remove(*labels)

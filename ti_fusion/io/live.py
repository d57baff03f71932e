"""The live view: a run's log served over the Foxglove WebSocket protocol while the run goes on.

    live = LiveServer("127.0.0.1:8765")                 # "0" picks a free port; live.url says where
    with RunLogger(path, metadata, live=live) as log:   # every message goes to the file and to the clients
        ...

``RunLogger`` is the one logging path: it hands every message it writes, as the same bytes, on a channel
with the same schema, to this sink too. The server is the one of Foxglove's SDK (``foxglove-sdk``): it
runs on its own threads outside the interpreter, and a channel that no client subscribes to drops a
message at once, so a live run with no client costs nothing measurable. Each client gets a bounded queue
(the oldest message is dropped when it is full), so a slow client never holds the run up. The map is the
one message that costs the run to make: the pipeline asks ``map_due()`` and sends a cloud of at most
``max_points`` points at most every ``map_period_s`` seconds, and only while a client watches it.

Time. The server has the ``time`` capability and sends the log time of each new message as the server's
time, so a live view's timeline and plots run on the dataset's time, as the file's do (without it a client
uses its wall clock).

The SDK speaks the protocol under the sub-protocol name ``foxglove.sdk.v1``, the same protocol as
``foxglove.websocket.v1`` renamed; current Foxglove and Lichtblick from 1.22.1 offer both names, and an older
client (Foxglove Studio, Lichtblick before 1.22.1) that offers only the old one is refused with HTTP 400. The
SDK logs "Dropping client ...: handshake failed" at each of its retries; ``LiveServer`` turns them into one
warning that says why. The SDK (0.30) can refuse, as an
"Unknown channel ID", a subscription that arrives in the instant after a channel is created while this
process is busy, so ``RunLogger`` creates its channels when the log opens, before a client is likely to
be connected; a client can subscribe again.
"""

from __future__ import annotations

import logging
import re
import threading
import time
import weakref

from ti_fusion.errors import InputError

DEFAULT_HOST = "127.0.0.1"  # loopback: a run is not served to the network unless a host is given
DEFAULT_PORT = 8765         # Foxglove's default for a WebSocket connection
MAP_TOPIC = "/map/points"
MAP_PERIOD_S = 1.0          # at most one live map a second ...
MAP_MAX_POINTS = 50_000     # ... of at most this many points (0.8 MB)
BACKLOG = 256               # messages queued per client before the oldest is dropped
LINGER_S = 0.25             # on closing, time for the clients' queues to drain (stopping drops what is queued)
CLOSE_TIMEOUT_S = 2.0       # the most closing waits for the server to stop (a client that never reads holds it)
# Logged once: sent again to a client that subscribes later (the trajectory and the mesh as the run closes too).
LATCHED = ("/camera/calibration", "/map/mesh", "/trajectory")
ANY_HOST = ("0.0.0.0", "::", "")  # every network interface
SDK_LOGGER = "foxglove.websocket.server"  # where the SDK's server logs (through Python's logging)
REFUSED = re.compile(r"Dropping client (.+?):\d+: handshake failed")
CLIENTS = ("current Foxglove and Lichtblick 1.22.1 or later offer it; Foxglove Studio and older Lichtblick "
           "offer only foxglove.websocket.v1 and cannot connect")

log = logging.getLogger(__name__)


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` → (host, port); the host defaults to loopback, port 0 picks a free one."""
    host, sep, port = str(text).strip().rpartition(":")
    host = host.strip("[]") if sep else DEFAULT_HOST
    if not port.isdigit() or int(port) > 65535 or (sep and not host):
        raise InputError(None, f"--live {text}: expected [HOST:]PORT, e.g. 8765 or 0.0.0.0:8765")
    return host, int(port)


class LiveServer:
    """A Foxglove WebSocket server fed by ``RunLogger``: channels are advertised as the log creates them."""

    def __init__(self, address: str = str(DEFAULT_PORT), map_period_s: float = MAP_PERIOD_S,
                 max_points: int = MAP_MAX_POINTS, name: str = "ti-fusion"):
        import foxglove  # the SDK's native module: loaded by live runs only

        self._foxglove = foxglove
        self.map_period_s = map_period_s
        self.max_points = max_points
        self._context = foxglove.Context()  # this server's channels, apart from any other SDK user's
        self._channels: dict = {}  # topic → foxglove.Channel
        self._latched: dict[str, tuple[bytes, int]] = {}  # topic → its last message and log time
        self._resend: set[str] = set()  # latched topics a client subscribed to since their last message
        self._map_sent = -float("inf")
        self._time_ns = -1  # the last time sent to the clients
        self._lock = threading.Lock()  # the server's threads call the listener
        host, port = parse_address(address)
        self.refused = 0  # clients refused so far (counted by _REFUSED)
        # Every channel a run logs exists before a client can connect: the SDK refuses ("Unknown channel ID") a
        # subscription that a client sends while the channel is being added, and a client never asks again.
        from ti_fusion.io.mcap_log import live_channel_specs

        for spec in live_channel_specs():
            self.add_channel(*spec)
        _REFUSED.servers.add(self)
        logging.getLogger(SDK_LOGGER).addFilter(_REFUSED)  # once for the process (a filter is added once)
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._context,
                                                 server_listener=_Listener(self), message_backlog_size=BACKLOG,
                                                 capabilities=[foxglove.websocket.Capability.Time])
        except Exception as exc:  # noqa: BLE001 - the SDK raises a RuntimeError with the OS's reason
            _REFUSED.servers.discard(self)
            raise InputError(None, f"--live {address}: cannot serve on {host}:{port}: {exc}") from None
        self.host, self.port = host, self._server.port
        self.closed = False

    @property
    def topics(self) -> list[str]:
        """The channels advertised so far."""
        return list(self._channels)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    @property
    def every_interface(self) -> bool:
        """Whether the server listens on every network interface (HOST 0.0.0.0 or ::)."""
        return self.host in ANY_HOST

    def urls(self) -> list[str]:
        """The URLs a client can use: the host given, or for every interface this machine's own addresses
        (loopback first), since ws://0.0.0.0 is no address a remote client can reach."""
        if not self.every_interface:
            return [self.url]
        hosts = ["127.0.0.1"] + [a for a in _own_addresses() if not a.startswith("127.")]
        return [f"ws://{f'[{h}]' if ':' in h else h}:{self.port}" for h in dict.fromkeys(hosts)]

    # -- what RunLogger calls ---------------------------------------------------------------------
    def add_channel(self, topic: str, message_encoding: str, schema_name: str, schema_encoding: str,
                    schema_data: bytes) -> None:
        """Advertise a channel (once: a topic advertised already keeps its channel)."""
        if topic in self._channels:
            return
        schema = self._foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
        self._channels[topic] = self._foxglove.Channel(topic, schema=schema, message_encoding=message_encoding,
                                                       context=self._context)

    def log(self, topic: str, data: bytes, ns: int) -> None:
        """One message to the clients subscribed to ``topic`` (none: dropped at once)."""
        if self.closed:
            return
        if topic in LATCHED:
            self._latched[topic] = (data, ns)
        elif topic == MAP_TOPIC:
            self._map_sent = time.monotonic()
        if self._resend:
            self._send_latched()
        if ns > self._time_ns:  # the dataset's time, for the clients' timeline (the time capability)
            self._time_ns = ns
            self._server.broadcast_time(ns)
        self._channels[topic].log(data, log_time=ns)

    def subscribed(self, topic: str) -> bool:
        """Whether a client subscribes to ``topic`` now."""
        channel = self._channels.get(topic)
        return channel is not None and not self.closed and channel.has_sinks()

    def map_due(self) -> bool:
        """Whether to send a live map now: a client watches it and the last one is ``map_period_s`` old."""
        if self.closed or time.monotonic() - self._map_sent < self.map_period_s:
            return False
        channel = self._channels.get(MAP_TOPIC)
        return channel is None or channel.has_sinks()  # not advertised yet: the first call advertises it

    def close(self) -> None:
        """Stop serving: clients get what is queued for them (when any subscribes), then see the connection
        close (idempotent)."""
        if not self.closed:
            self.closed = True
            try:
                if any(channel.has_sinks() for channel in self._channels.values()):
                    time.sleep(LINGER_S)  # the SDK has no flush: its sender threads drain the queues meanwhile
                    if self._resend:  # subscribed to the trajectory or the mesh just as they were logged
                        self._send_latched()
                        time.sleep(LINGER_S)
            finally:  # a second Ctrl-C during the wait still stops the server
                _REFUSED.servers.discard(self)
                self._stop_bounded()

    def _stop_bounded(self) -> None:
        """Stop the server, waiting at most CLOSE_TIMEOUT_S: the SDK's stop waits for every client's close
        handshake, which a client that stopped reading never completes; the run's end must not wait for it."""
        stopper = threading.Thread(target=self._server.stop, name="ti-fusion-live-stop", daemon=True)
        stopper.start()
        stopper.join(CLOSE_TIMEOUT_S)
        if stopper.is_alive():
            log.warning(f"live: a client did not take what was sent to it: stopped serving without waiting for it "
                        f"(after {CLOSE_TIMEOUT_S:g} s)")

    # -- internals --------------------------------------------------------------------------------
    def _subscribed(self, topic: str) -> None:
        if topic in LATCHED:
            with self._lock:
                self._resend.add(topic)

    def _send_latched(self) -> None:
        with self._lock:
            topics, self._resend = self._resend, set()
        for topic in topics:
            if topic in self._latched:
                data, ns = self._latched[topic]
                self._channels[topic].log(data, log_time=ns)


def _own_addresses() -> list[str]:
    """This machine's IPv4 addresses as far as the host name and the default route tell (no packet is sent)."""
    import socket

    found = []
    try:
        found += socket.gethostbyname_ex(socket.gethostname())[2]
    except OSError:
        pass
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1: a UDP connect only picks the outgoing interface
            found.append(probe.getsockname()[0])
    except OSError:
        pass
    return list(dict.fromkeys(found))


class _RefusedClients(logging.Filter):
    """Turns the SDK's "Dropping client HOST:PORT: handshake failed" records, one per retry of a refused
    client, into one warning for a server's first (what most likely happened and which clients connect);
    the rest are dropped. One filter for the process, since a record does not say which server refused: it
    counts for every open server."""

    def __init__(self):
        super().__init__()
        self.servers: weakref.WeakSet = weakref.WeakSet()

    def filter(self, record: logging.LogRecord) -> bool:
        match = REFUSED.search(record.getMessage())
        if match is None:
            return True
        servers = list(self.servers)
        for server in servers:
            server.refused += 1
        if any(server.refused == 1 for server in servers):
            log.warning(f"live: refused a client at {match.group(1)}: its WebSocket handshake failed, most likely "
                        f"because it does not offer the sub-protocol foxglove.sdk.v1 ({CLIENTS}); further "
                        "refusals are not shown")
        return False


_REFUSED = _RefusedClients()


class _Listener:
    """The server's callbacks (on its own threads): a subscription to a latched topic asks for a resend."""

    def __init__(self, server: LiveServer):
        self._server = server

    def on_subscribe(self, client, channel) -> None:
        self._server._subscribed(channel.topic)

    def on_unsubscribe(self, client, channel) -> None:
        pass  # has_sinks() says whether any client still subscribes

"""The live session's web page (``mirror-fg live --serve PORT``), on Tornado (a Dask dependency already).

Served on 127.0.0.1 only, from a thread with its own event loop, so the frame loop never waits for it:

- ``/``: the page (``live_page.html``): the picture with its detections, the 3-sigma bounds as bars
  against the targets (green when met), a polar plot of the mirror's tilt now, the suggested one and
  the placements so far, the next suggestion in words, and the stop message;
- ``/events``: server-sent events, the newest JSON status (one event per response, EventSource
  reconnecting at once: at most ~20 a second);
- ``/frame.jpg``: the newest picture (JPEG, at most ~10 new ones a second).

Every route answers only requests addressed to this server by its loopback name: a ``Host`` other than
``127.0.0.1:PORT``, ``localhost:PORT`` or ``[::1]:PORT`` gets 421 and an ``Origin`` other than
``http://`` one of those gets 403, so a web site whose name is rebound to 127.0.0.1 (DNS rebinding)
cannot read the picture or the status from the user's browser. Nothing else is protected: any program
running on this machine can read the page, which has no login.
"""
from __future__ import annotations

import asyncio
import json
import socket
import threading
from importlib import resources
from typing import Any, Callable

from mirror_fg.core.errors import DatasetError

__all__ = ["LiveServer", "allowed_hosts", "refusal"]

#: How often an event request looks for a new state, and how long it waits for one (seconds).
EVENT_PERIOD_S, EVENT_WAIT_S = 0.05, 0.25
#: The browser reconnects this soon after each event (milliseconds).
RETRY_MS = 50


def allowed_hosts(port: int) -> frozenset[str]:
    """The ``Host`` values of a request addressed to this server on ``port`` by its loopback name."""
    return frozenset(f"{name}:{port}" for name in ("127.0.0.1", "localhost", "[::1]"))


def refusal(host: str | None, origin: str | None, port: int) -> tuple[int, str] | None:
    """``(status, reason)`` to refuse a request with this ``Host`` and ``Origin`` header, None to serve it:
    421 for another host name (a rebound DNS name), 403 for a page of another origin."""
    hosts = allowed_hosts(port)
    if (host or "").lower() not in hosts:
        return 421, "this page answers only to 127.0.0.1, localhost or [::1] on its port"
    if origin is not None and origin.lower() not in {f"http://{h}" for h in hosts}:
        return 403, "requests from other web pages are refused"
    return None


class LiveServer:
    """``state()`` returns the session's current :class:`~mirror_fg.live.session.LiveState`."""

    def __init__(self, port: int, state: Callable[[], object]):
        self.state = state
        self.requested_port = port
        self.port: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def start(self) -> None:
        """Listen (127.0.0.1) and serve from a background thread; DatasetError when the port is taken."""
        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(("127.0.0.1", self.requested_port))
            sock.listen(64)
            sock.setblocking(False)
        except OSError as error:
            raise DatasetError(f"--serve {self.requested_port}: cannot listen on 127.0.0.1:{self.requested_port} "
                               f"({error.strerror or error})") from None
        self.port = sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, args=(sock,), name="mirror-fg live page", daemon=True)
        self._thread.start()
        self._started.wait(10.0)
        if self._error is not None:
            raise DatasetError(f"--serve {self.requested_port}: {self._error}")

    def _run(self, sock: socket.socket) -> None:
        import tornado.httpserver
        import tornado.web

        state = self.state
        assert self.port is not None
        port = self.port
        page = resources.files("mirror_fg.live").joinpath("live_page.html").read_bytes()

        class Local(tornado.web.RequestHandler):
            """Every route: only for this server's loopback names (DNS rebinding, see the module header)."""

            def prepare(self) -> None:
                refused = refusal(self.request.headers.get("Host"), self.request.headers.get("Origin"), port)
                if refused is not None:
                    self.set_status(refused[0])
                    self.set_header("Content-Type", "text/plain; charset=utf-8")
                    self.finish(refused[1] + "\n")

        class Missing(Local):
            def get(self) -> None:
                raise tornado.web.HTTPError(404)

        class Page(Local):
            def get(self) -> None:
                self.set_header("Content-Type", "text/html; charset=utf-8")
                self.write(page)

        class Frame(Local):
            def get(self) -> None:
                jpeg = getattr(state(), "jpeg", b"")
                if not jpeg:
                    self.set_status(204)
                    return
                self.set_header("Content-Type", "image/jpeg")
                self.set_header("Cache-Control", "no-store")
                self.write(jpeg)

        class Events(Local):
            """One event per response: the newest state once it differs from the client's Last-Event-ID
            (waiting up to EVENT_WAIT_S for it), then the stream ends and EventSource reconnects after
            ``retry`` ms. Short responses keep no request pending (a headless browser's virtual time
            and a proxy's timeouts both need that)."""

            async def get(self) -> None:
                self.set_header("Content-Type", "text/event-stream")
                self.set_header("Cache-Control", "no-store")
                last = self.request.headers.get("Last-Event-ID")
                waited = 0.0
                current = state()
                while str(current.seq) == last and waited < EVENT_WAIT_S:  # type: ignore[attr-defined]
                    await asyncio.sleep(EVENT_PERIOD_S)
                    waited += EVENT_PERIOD_S
                    current = state()
                self.write(f"retry: {RETRY_MS}\n")
                if str(current.seq) != last and current.status:  # type: ignore[attr-defined]
                    self.write(f"id: {current.seq}\ndata: {json.dumps(current.status)}\n\n")  # type: ignore[attr-defined]
                else:
                    self.write(": no new frame\n\n")
                self.finish()

        try:
            self._loop = asyncio.new_event_loop()
            asyncio.set_event_loop(self._loop)
            app = tornado.web.Application([("/", Page), ("/frame.jpg", Frame), ("/events", Events)],
                                          default_handler_class=Missing)
            self._server = tornado.httpserver.HTTPServer(app)
            self._server.add_sockets([sock])
        except Exception as error:  # noqa: BLE001 - reported to start() as one line
            self._error = error
            self._started.set()
            return
        self._started.set()
        self._loop.run_forever()

    def stop(self) -> None:
        if self._loop is None:
            return
        loop = self._loop

        def shutdown() -> None:
            if self._server is not None:
                self._server.stop()
            loop.stop()

        loop.call_soon_threadsafe(shutdown)
        if self._thread is not None:
            self._thread.join(timeout=5.0)

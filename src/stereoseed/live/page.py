"""The live page: served on 127.0.0.1 only (nothing listens elsewhere), updated by server push
(Server-Sent Events on ``/events``: each message the whole state and the log's last
``LiveConfig.log_lines`` lines, so a browser that reconnects loses nothing; the state is turned
into JSON once per state, not once per message), every asset served by this process (Plotly's bundle from the installed package,
the one report.html inlines): the page works with no internet.

    page = LivePage(port=0)       # 0: a free port; page.url
    page.publish(state)           # the run's state (stereoseed.live.status.page_state)
    page.event("IMG_7.jpg: ...")  # a line in the page's log
    page.close()

A browser that goes away is noticed at the next write (a heartbeat comment every
``LiveConfig.heartbeat_s``), said in a line, and its connection closed; the run goes on.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from stereoseed.errors import StereoseedError
from stereoseed.io.atomic import jsonable
from stereoseed.live.config import LiveConfig
from stereoseed.live.page_html import PAGE_HTML

__all__ = ["LivePage", "HOST"]

log = logging.getLogger(__name__)

HOST = "127.0.0.1"  # the page shows the user's photos and model: this machine only


class LivePage:
    """The page's server, in a thread of its own (and one per connected browser)."""

    def __init__(self, port: int = 0, cfg: LiveConfig = LiveConfig(), title: str = "stereoseed live"):
        self.cfg = cfg
        self.title = title
        self._cond = threading.Condition()
        self._version = 0
        self._state_json = b"{}"  # the state as published, in JSON
        self._events: deque[dict[str, Any]] = deque(maxlen=cfg.log_lines)
        self._closing = False
        self._plotly: bytes | None = None
        self.delivered: dict[int, float] = {}  # version -> when a browser first got it (monotonic s)
        page = self

        class Handler(_Handler):
            live = page

        try:
            self.server = ThreadingHTTPServer((HOST, port), Handler)
        except OSError as e:
            raise StereoseedError(f"port {port}: cannot serve the live page there ({e.strerror or e}); give another "
                                  f"--port, or 0 for a free one") from None
        self.server.daemon_threads = True
        self.port = self.server.server_address[1]
        self._thread = threading.Thread(target=self.server.serve_forever, name="stereoseed-live-page", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    # ------------------------------------------------------------------ what the run says
    def publish(self, state: dict[str, Any]) -> int:
        """The run's state as it stands now; returns its version."""
        body = json.dumps(state, default=jsonable).encode()  # once, here, not in every message
        with self._cond:
            self._state_json = body
            self._version += 1
            self._cond.notify_all()
            return self._version

    def event(self, line: str, level: str = "info") -> None:
        """A line in the page's log (``level``: info, warning)."""
        with self._cond:
            self._events.append({"t": time.strftime("%H:%M:%S"), "level": level, "line": line})
            self._version += 1
            self._cond.notify_all()

    @property
    def version(self) -> int:
        with self._cond:
            return self._version

    def message(self) -> tuple[int, bytes]:
        """(version, the whole state and log as one JSON text)."""
        with self._cond:
            version, state, events = self._version, self._state_json, list(self._events)
        return version, b'{"version": %d, "state": %s, "events": %s}' % (version, state, json.dumps(events).encode())

    def wait_past(self, version: int, timeout: float) -> bool:
        """Wait until the state is newer than ``version`` (True) or ``timeout`` s (False) or closing."""
        with self._cond:
            return self._cond.wait_for(lambda: self._version > version or self._closing, timeout) and not self._closing

    def plotly_js(self) -> bytes:
        if self._plotly is None:
            from plotly.offline import get_plotlyjs  # the bundle report.html inlines

            self._plotly = get_plotlyjs().encode("utf-8")
        return self._plotly

    def close(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5)

    def __enter__(self) -> LivePage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Handler(BaseHTTPRequestHandler):
    live: LivePage
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        log.debug("live page: " + format, *args)

    def _send(self, body: bytes, content_type: str, status: int = 200) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:  # noqa: N802 - the base class's name
        path = self.path.split("?", 1)[0]
        try:
            if path == "/":
                self._send(PAGE_HTML.replace("{{TITLE}}", self.live.title).encode("utf-8"), "text/html; charset=utf-8")
            elif path == "/plotly.js":
                self._send(self.live.plotly_js(), "text/javascript; charset=utf-8")
            elif path == "/state":
                self._send(self.live.message()[1], "application/json")
            elif path == "/events":
                self._stream()
            else:
                self._send(b"not found\n", "text/plain; charset=utf-8", 404)
        except (BrokenPipeError, ConnectionResetError, ConnectionAbortedError):
            pass  # a browser that left while a file was sent: nothing to say

    def _stream(self) -> None:
        """Server-Sent Events: the whole state at once, then at each change; a heartbeat
        comment between them."""
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        who = f"{self.client_address[0]}:{self.client_address[1]}"
        live = self.live
        version = -1
        try:
            while not live._closing:
                if version < live.version:
                    version, body = live.message()
                    self.wfile.write(b"id: %d\ndata: " % version + body + b"\n\n")
                    self.wfile.flush()
                    live.delivered.setdefault(version, time.monotonic())
                elif not live.wait_past(version, live.cfg.heartbeat_s) and not live._closing:
                    self.wfile.write(b": still here\n\n")
                    self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError) as e:
            if not live._closing:
                log.info("live page: the browser at %s disconnected (%s)", who, type(e).__name__)
                live.event(f"a browser disconnected ({who}); the run goes on, and reloading the page shows all of it",
                           "warning")

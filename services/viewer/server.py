"""`roadmap viewer [--connect EP | --from DIR] [--port P]`: the viewer's HTTP server (standard
library, one thread per request) on 127.0.0.1 by default.

    /                      the page (static/index.html; static/app.js, static/style.css)
    /api/state             JSON: tiles with versions and shards, poses, shards, classes
    /api/tile/TX/TY.png    a tile in the map palette, north up (no data transparent)
    /api/tile/TX/TY        JSON: the tile's version, codec, size and its shard's counters"""

import json
import logging
import re
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

from common.errors import CodecError, RoadmapError
from services.viewer.state import ViewerState

logger = logging.getLogger(__name__)

STATIC = {"index.html": "text/html; charset=utf-8", "app.js": "text/javascript; charset=utf-8",
          "style.css": "text/css; charset=utf-8"}
TILE_RE = re.compile(r"^/api/tile/(-?\d+)/(-?\d+)(\.png)?$")


class ViewerError(RoadmapError):
    """The viewer cannot serve (port taken, nothing to show)."""


def static_file(name: str) -> bytes:
    return resources.files("services.viewer").joinpath("static", name).read_bytes()


class _Handler(BaseHTTPRequestHandler):
    server_version = "roadmap-viewer"
    state: ViewerState  # set on the subclass made per server
    refresh_stats = None  # a live feed's: fresh shard stats for a clicked tile

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        path = self.path.split("?", 1)[0]
        try:
            if path in ("/", "/index.html"):
                self._send(HTTPStatus.OK, STATIC["index.html"], static_file("index.html"))
            elif path.startswith("/static/") and path[len("/static/"):] in STATIC:
                name = path[len("/static/"):]
                self._send(HTTPStatus.OK, STATIC[name], static_file(name))
            elif path == "/api/state":
                self._json(self.state.snapshot())
            elif m := TILE_RE.match(path):
                self._tile((int(m.group(1)), int(m.group(2))), png=bool(m.group(3)))
            else:
                self._send(HTTPStatus.NOT_FOUND, "text/plain", b"not found\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the page went away mid-answer
        except CodecError as exc:
            self._send(HTTPStatus.INTERNAL_SERVER_ERROR, "text/plain", f"{exc}\n".encode())

    def _tile(self, tile, png: bool) -> None:
        if not png and self.refresh_stats is not None:
            try:
                self.refresh_stats()
            except Exception as exc:  # the panel shows the last stats instead
                logger.warning("stats for tile %s: %s", tile, exc)
        body = self.state.png(tile) if png else self.state.tile_info(tile)
        if body is None:
            self._send(HTTPStatus.NOT_FOUND, "text/plain", f"no tile {tile}\n".encode())
        elif png:
            self._send(HTTPStatus.OK, "image/png", body, cache=True)
        else:
            self._json(body)

    def _json(self, obj) -> None:
        self._send(HTTPStatus.OK, "application/json", json.dumps(obj).encode())

    def _send(self, status, ctype: str, body: bytes, cache: bool = False) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        # a PNG is asked for with its version (?v=N): that URL's content never changes
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, fmt, *args) -> None:
        logger.debug("%s %s", self.address_string(), fmt % args)


def serve(state: ViewerState, host: str, port: int, refresh_stats=None) -> ThreadingHTTPServer:
    """An HTTP server for `state`, serving from a daemon thread; call shutdown() to stop.
    `refresh_stats()`, when given, is called before a tile's panel is answered."""
    handler = type("Handler", (_Handler,), {"state": state,
                                            "refresh_stats": staticmethod(refresh_stats)
                                            if refresh_stats else None})
    try:
        httpd = ThreadingHTTPServer((host, port), handler)
    except OSError as exc:
        raise ViewerError(f"cannot serve on {host}:{port}: {exc}") from exc
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, name="viewer-http", daemon=True).start()
    return httpd


def viewer_command(args, cfg) -> int:
    from common.bus import open_session, stop_event

    stop = stop_event()
    if args.from_dir:
        from services.viewer.feed import load_folder

        state = ViewerState(source=f"folder {args.from_dir}")
        load_folder(state, args.from_dir)
        return _serve_until(stop, state, args)
    from services.viewer.feed import LiveFeed

    state = ViewerState(source=f"fleet via {', '.join(cfg.bus.connect)}")
    with open_session(cfg.bus) as session:
        feed = LiveFeed(session, state, ident=f"port{args.port}",
                        stats_every_s=args.stats_every,
                        timeout_s=min(cfg.bus.query_timeout_s, 2.0)).start()
        try:
            return _serve_until(stop, state, args, refresh_stats=feed.refresh_stats)
        finally:
            feed.close()


def _serve_until(stop: threading.Event, state: ViewerState, args, refresh_stats=None) -> int:
    httpd = serve(state, args.host, args.port, refresh_stats)
    url = f"http://{args.host}:{httpd.server_address[1]}/"
    sys.stderr.write(f"roadmap viewer: {url} ({state.source}); Ctrl-C stops\n")
    try:
        stop.wait()
    finally:
        httpd.shutdown()
        httpd.server_close()
    return 0

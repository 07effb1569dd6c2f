"""The twin in a browser: a read-only HTTP server for one twin's files and the page that draws them.

URL layout (GET only; everything else is refused):

    /                   the page (deploy/web/index.html)
    /web/<file>         the page's own script and style (deploy/web/)
    /vendor/<file>      three.js and Spark, copied from the npm packages at `make env` (deploy/web/vendor/)
    /twin/<file>        the twin's files: twin.json, splats.ply, mesh_*.glb, renders/ ...
    /inspection/<file>  the twin's inspection report (`cadsplat inspect`), when it has one

A path is served only when it resolves, links followed, to a regular file inside its folder
(`calibration.guard.contained`), and no name in it starts with a dot (the `.incoming` folders of a twin
being written). Bound to loopback the server needs nothing else; bound to any other interface every
request must carry the token it was started with: in the URL's `token=` once, then in the cookie the
server sets with that answer.
"""

from __future__ import annotations

import hmac
import ipaddress
import mimetypes
import secrets
import socket
import threading
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

from calibration.guard import PathOutside, contained

WEB_DIR = Path(__file__).resolve().parent / "web"
VENDOR_DIR = WEB_DIR / "vendor"
COOKIE = "cadsplat_view"
# Served types the page needs; module scripts are refused by browsers under any other type than JavaScript.
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".png": "image/png",
    ".glb": "model/gltf-binary",
    ".ply": "application/octet-stream",
    ".spz": "application/octet-stream",
    ".csv": "text/csv; charset=utf-8",
    ".txt": "text/plain; charset=utf-8",
}


@dataclass(frozen=True)
class ViewRoots:
    """The folders the server reads, by the URL prefix that names them. inspection: None when the twin has none."""

    twin: Path
    inspection: Path | None = None
    web: Path = WEB_DIR
    vendor: Path = VENDOR_DIR

    def folder(self, prefix: str) -> Path | None:
        return {"twin": self.twin, "inspection": self.inspection, "web": self.web, "vendor": self.vendor}.get(prefix)


def resolve_url_path(roots: ViewRoots, url_path: str) -> Path | None:
    """The file `url_path` (already split from its query) names, or None when it names nothing servable.

    None for: an unknown prefix, `..` or a dot-name anywhere, a path that leads (by links too) outside its
    folder, anything that is not a regular file.
    """
    path = unquote(url_path)
    if path in ("", "/"):
        path = "/web/index.html"
    head, _, rest = path.lstrip("/").partition("/")
    folder = roots.folder(head)
    parts = rest.split("/")
    if folder is None or not rest or any(p in ("", ".", "..") or p.startswith(".") or "\\" in p or "\0" in p for p in parts):
        return None
    try:
        target = contained(folder, rest)
    except PathOutside:
        return None
    return target if target.is_file() else None


def is_loopback(host: str) -> bool:
    """True for an address only this machine reaches (127.0.0.0/8, ::1, `localhost`)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class ViewServer(ThreadingHTTPServer):
    """ThreadingHTTPServer over `roots`; token None on loopback (nothing to ask), else the secret every request carries."""

    daemon_threads = True
    allow_reuse_address = False

    def __init__(self, roots: ViewRoots, host: str = "127.0.0.1", port: int = 0, token: str | None = None):
        if not is_loopback(host) and not token:
            raise ValueError(f"serving on {host} (not loopback) needs a token")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.address_family = family
        self.roots, self.token, self.host = roots, token, host
        super().__init__((host, port), ViewHandler)

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    def url(self, query: str = "") -> str:
        """The page's address, with the token when one is needed (a wildcard host is shown as this machine's name)."""
        host = self.host
        if host in ("0.0.0.0", "::"):
            host = socket.gethostname()
        elif ":" in host:
            host = f"[{host}]"
        params = "&".join(p for p in (f"token={self.token}" if self.token else "", query) if p)
        return f"http://{host}:{self.port}/" + (f"?{params}" if params else "")


class ViewHandler(BaseHTTPRequestHandler):
    server: ViewServer
    server_version = "cadsplat-view"
    sys_version = ""

    def log_message(self, format: str, *args) -> None:
        pass

    def _authorised(self, query: dict[str, list[str]]) -> tuple[bool, bool]:
        """(allowed, set the cookie): the token from the query (then set as a cookie) or from the cookie."""
        token = self.server.token
        if token is None:
            return True, False
        given = query.get("token", [""])[0]
        if given and hmac.compare_digest(given.encode(), token.encode()):
            return True, True
        for part in self.headers.get("Cookie", "").split(";"):
            name, _, value = part.strip().partition("=")
            if name == COOKIE and hmac.compare_digest(value.encode(), token.encode()):
                return True, False
        return False, False

    def _host_allowed(self) -> bool:
        # On loopback, a page from elsewhere must not reach the server through a name that resolves to 127.0.0.1
        # (DNS rebinding): only requests addressed to a loopback name are answered.
        if self.server.token is not None:
            return True
        host = self.headers.get("Host", "")
        name = host[1:].partition("]")[0] if host.startswith("[") else host.rpartition(":")[0] or host
        return is_loopback(name)

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        allowed, set_cookie = self._authorised(parse_qs(url.query))
        if not allowed or not self._host_allowed():
            self.send_error(HTTPStatus.FORBIDDEN, "a token is needed: open the URL `cadsplat view` printed")
            return
        target = resolve_url_path(self.server.roots, url.path)
        if target is None:
            self.send_error(HTTPStatus.NOT_FOUND)
            return
        try:
            data = target.read_bytes()
        except OSError:
            self.send_error(HTTPStatus.NOT_FOUND)
            return
        self.send_response(HTTPStatus.OK)
        kind = CONTENT_TYPES.get(target.suffix.lower()) or mimetypes.guess_type(target.name)[0] or "application/octet-stream"
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        if set_cookie:
            self.send_header("Set-Cookie", f"{COOKIE}={self.server.token}; HttpOnly; SameSite=Strict; Path=/")
        self.end_headers()
        self.wfile.write(data)


def new_token() -> str:
    return secrets.token_urlsafe(24)


def serve_until(server: ViewServer, stop: threading.Event) -> None:
    """Serve on a thread until `stop` is set, then close the socket; returns when the server has stopped."""
    thread = threading.Thread(target=server.serve_forever, name="cadsplat-view", daemon=True)
    thread.start()
    try:
        stop.wait()
    finally:
        server.shutdown()
        server.server_close()
        thread.join()

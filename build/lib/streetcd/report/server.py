"""``streetcd serve``: the review page live, recording decisions into the change index.

A standard-library threaded HTTP server over a site built at start (:func:`build_site`, into
a temporary folder). Everything is read-only except one request::

    GET  /, /index.html         the page
    GET  /data.js               the page's data, read from the index at each request
    GET  /assets/*, /thumbs/*   files of the built site (resolved inside it, never outside)
    GET  /full/<view>           the full-size image of a view the page shows (by name)
    POST /api/review            {"id", "status", "note"?, "who"?}: record a decision

Bound to a loopback address by default. Bound to any other address, every request needs the
token (``?token=`` once, then a cookie; or the ``X-Streetcd-Token`` header). A decision must
come as ``application/json`` from the page's own origin, so another site open in the same
browser cannot post one. The index is written only through
:func:`streetcd.report.changes.record_decision` (parameterised SQL in ``store.objects``).
"""

from __future__ import annotations

import getpass
import hmac
import ipaddress
import json
import mimetypes
import secrets
import shutil
import socket
import tempfile
import threading
from http.cookies import SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import parse_qs, quote, unquote, urlsplit

from streetcd.errors import InputError, MissingInputError, StreetcdError
from streetcd.report.changes import load_changes, record_decision
from streetcd.report.site import Site, build_site, data_script, page_data

MAX_BODY_BYTES = 64 * 1024
STATIC_FOLDERS = ("assets", "thumbs")
CSP = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or address) is this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def static_file(root: Path, url_path: str) -> Path | None:
    """The file of the built site that ``url_path`` (as requested, percent-encoded) names,
    or None when it names nothing there: only plain files under ``assets/`` or ``thumbs/``,
    no ``..``, no absolute or drive paths, no escape through a link."""
    path = unquote(url_path)
    if "\x00" in path or "\\" in path:
        return None
    parts = PurePosixPath(path.lstrip("/")).parts
    if len(parts) < 2 or parts[0] not in STATIC_FOLDERS or any(p in ("..", ".") for p in parts):
        return None
    root = root.resolve()
    target = root.joinpath(*parts).resolve()
    if not target.is_relative_to(root) or not target.is_file():
        return None
    return target


class ReviewServer(ThreadingHTTPServer):
    """The server: the index, the built site and the token (None on loopback)."""

    daemon_threads = True

    def __init__(
        self,
        address: tuple[str, int],
        index: Path,
        site: Site,
        site_dir: Path,
        *,
        token: str | None,
        run_id: str | None,
        reviewer: str,
        owns_site_dir: bool = False,
    ):
        if ":" in address[0]:  # an IPv6 address such as ::1
            self.address_family = socket.AF_INET6
        super().__init__(address, ReviewHandler)
        self.owns_site_dir = owns_site_dir  # a temporary folder, removed on close
        self.index = index
        self.site = site
        self.site_dir = site_dir
        self.token = token
        self.run_id = run_id
        self.reviewer = reviewer
        # one decision at a time: SQLite serialises writers anyway; this keeps the answers in order
        self.write_lock = threading.Lock()
        self.images = {v: m["image"] for v, m in site.media.items() if m.get("image")}

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        host = host.decode() if isinstance(host, bytes) else str(host)
        shown = f"[{host}]" if ":" in host else host
        query = f"?token={self.token}" if self.token else ""
        return f"http://{shown}:{port}/{query}"

    def live_data(self) -> bytes:
        changes = load_changes(self.index)
        data = page_data(
            self.index,
            changes,
            self.site.media,
            self.site.sources,
            lambda view, _p: "full/" + _quote(view),
            run_id=self.run_id,
            live=True,
        )
        return data_script(data)


def _quote(text: str) -> str:
    return quote(text, safe="")


class ReviewHandler(BaseHTTPRequestHandler):
    server: ReviewServer
    server_version = "streetcd-serve"
    sys_version = ""

    # --- plumbing -------------------------------------------------------------------------

    def log_message(self, format: str, *args: Any) -> None:  # the base class names it so
        pass  # quiet: the terminal shows the URL and errors, not every thumbnail

    def _send(
        self, code: int, body: bytes, ctype: str, extra: dict[str, str] | None = None
    ) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", CSP)
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Cache-Control", "no-store")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _text(self, code: int, text: str) -> None:
        self._send(code, (text + "\n").encode(), "text/plain; charset=utf-8")

    def _token_ok(self, query: dict[str, list[str]], allow_query: bool) -> tuple[bool, bool]:
        """(allowed, came in the query). Loopback servers have no token."""
        want = self.server.token
        if want is None:
            return True, False
        given = self.headers.get("X-Streetcd-Token")
        if given is None:
            cookie = SimpleCookie(self.headers.get("Cookie", ""))
            given = cookie["streetcd_token"].value if "streetcd_token" in cookie else None
        from_query = False
        if given is None and allow_query and query.get("token"):
            given, from_query = query["token"][0], True
        ok = given is not None and hmac.compare_digest(given.encode(), want.encode())
        return ok, ok and from_query

    # --- GET ------------------------------------------------------------------------------

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        ok, set_cookie = self._token_ok(parse_qs(url.query), allow_query=True)
        if not ok:
            self._text(403, "403: this server needs its token (?token=...)")
            return
        extra = (
            {"Set-Cookie": f"streetcd_token={self.server.token}; HttpOnly; SameSite=Strict; Path=/"}
            if set_cookie
            else None
        )
        try:
            self._get(url.path, extra)
        except StreetcdError as exc:
            self._text(500, f"500: {exc}")

    do_HEAD = do_GET

    def _get(self, path: str, extra: dict[str, str] | None) -> None:
        root = self.server.site_dir
        if path in ("/", "/index.html"):
            body = (root / "index.html").read_bytes()
            self._send(200, body, "text/html; charset=utf-8", extra)
        elif path == "/data.js":
            self._send(200, self.server.live_data(), "text/javascript; charset=utf-8", extra)
        elif path.startswith("/full/"):
            image = self.server.images.get(unquote(path[len("/full/") :]))
            if image is None or not Path(image).is_file():
                self._text(404, "404: no such view")
                return
            ctype = mimetypes.guess_type(str(image))[0] or "application/octet-stream"
            self._send(200, Path(image).read_bytes(), ctype, extra)
        else:
            target = static_file(root, path)
            if target is None:
                self._text(404, "404: not found")
                return
            ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
            if ctype.startswith("text/") or ctype.endswith("javascript"):
                ctype += "; charset=utf-8"
            self._send(200, target.read_bytes(), ctype, extra)

    # --- POST: the one write --------------------------------------------------------------

    def do_POST(self) -> None:
        url = urlsplit(self.path)
        if url.path != "/api/review":
            self._text(404, "404: not found")
            return
        ok, _ = self._token_ok({}, allow_query=False)
        if not ok:
            self._text(403, "403: this server needs its token (X-Streetcd-Token)")
            return
        problem = self._check_origin_and_type()
        if problem:
            self._text(403 if "origin" in problem else 415, problem)
            return
        try:
            decision = self._read_decision()
        except InputError as exc:
            self._text(400, f"400: {exc}")
            return
        try:
            with self.server.write_lock:
                review = record_decision(self.server.index, **decision)
        except MissingInputError as exc:
            self._text(404, f"404: {exc}")
            return
        except StreetcdError as exc:
            self._text(400, f"400: {exc}")
            return
        body = json.dumps({"id": decision["change_id"], "review": review}).encode()
        self._send(200, body, "application/json")

    def _check_origin_and_type(self) -> str | None:
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return "415: a decision is sent as application/json"
        origin = self.headers.get("Origin")
        host = self.headers.get("Host")
        if origin is not None and origin != f"http://{host}":
            return f"403: origin {origin} is not this page's"
        return None

    def _read_decision(self) -> dict[str, Any]:
        try:
            length = int(self.headers.get("Content-Length") or "0")
        except ValueError:
            raise InputError("Content-Length is not a number") from None
        if not 0 < length <= MAX_BODY_BYTES:
            raise InputError(f"a decision is 1 to {MAX_BODY_BYTES} bytes, got {length}")
        try:
            body = json.loads(self.rfile.read(length))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"the decision is not JSON ({exc})") from None
        if not isinstance(body, dict) or not isinstance(body.get("id"), str | int):
            raise InputError('a decision is {"id": ..., "status": ..., "note": ...}')
        note, who = body.get("note"), body.get("who") or self.server.reviewer
        if note is not None and (not isinstance(note, str) or len(note) > 2000):
            raise InputError("note must be text of at most 2000 characters")
        if not isinstance(who, str) or len(who) > 100:
            raise InputError("who must be text of at most 100 characters")
        return {
            "change_id": str(body["id"]),
            "status": str(body.get("status")),
            "who": who,
            "note": note,
        }


def make_server(
    index: str | Path,
    *,
    host: str = "127.0.0.1",
    port: int = 8765,
    token: str | None = None,
    run_id: str | None = None,
    site_dir: str | Path | None = None,
    reviewer: str | None = None,
) -> ReviewServer:
    """Build the site (into ``site_dir``, default a new temporary folder) and bind the server
    (``port`` 0: any free port). A token is made when ``host`` is not loopback and none is
    given. Call ``serve_forever()``, then :func:`close_server`."""
    index = Path(index)
    if not index.is_file():
        raise MissingInputError(f"change index not found: {index}")
    folder = Path(site_dir) if site_dir else Path(tempfile.mkdtemp(prefix="streetcd-serve-"))
    site = build_site(
        index,
        folder,
        run_id=run_id,
        full_link=lambda view, _p: "full/" + _quote(view),
        live=True,
    )
    if token is None and not is_loopback(host):
        token = secrets.token_urlsafe(24)
    server = ReviewServer(
        (host, port),
        index,
        site,
        folder,
        token=token,
        run_id=run_id,
        reviewer=reviewer or _user(),
        owns_site_dir=site_dir is None,
    )
    return server


def close_server(server: ReviewServer) -> None:
    """Stop listening and remove the temporary site (a site folder given is kept)."""
    server.server_close()
    if server.owns_site_dir:
        shutil.rmtree(server.site_dir, ignore_errors=True)


def _user() -> str:
    try:
        return getpass.getuser()
    except (OSError, KeyError):
        return "reviewer"

"""HTTP for the editor and judge clients: credentials stay with the host they were meant for.

urllib's default opener follows redirects, keeping the ``Authorization`` header (a server
answering ``302 Location: http://elsewhere/`` received the key), and opens any scheme an
answer names (``file:///etc/...``). ``open_url`` follows no redirect (the error says where it
pointed) and accepts only http(s); ``fetch_url`` (an image a server returns by URL) also
accepts ``data:``.
"""

from __future__ import annotations

import urllib.error
import urllib.parse
import urllib.request

SCHEMES = ("http", "https")


class Redirected(urllib.error.URLError):
    """A redirect the client did not follow (the request may carry credentials)."""


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, req, fp, code, msg, headers, newurl):
        raise Redirected(f"HTTP {code}: redirected to {newurl} (not followed: requests carry credentials; "
                         f"configure the final URL)")


_OPENER = urllib.request.build_opener(_NoRedirect)


def _check_scheme(url: str, allowed: tuple[str, ...]) -> None:
    scheme = urllib.parse.urlsplit(url).scheme.lower()
    if scheme not in allowed:
        raise urllib.error.URLError(f"refusing {scheme or 'a relative'} URL {url[:80]!r}: only {', '.join(allowed)} "
                                    f"URLs are opened")


def open_url(req: urllib.request.Request | str, timeout: float):
    """``urlopen`` without redirects, for http(s) only (raises ``URLError`` otherwise)."""
    _check_scheme(req.full_url if isinstance(req, urllib.request.Request) else req, SCHEMES)
    return _OPENER.open(req, timeout=timeout)


def fetch_url(url: str, timeout: float) -> bytes:
    """The body at an http(s) or ``data:`` URL (no credentials are sent, no redirect followed)."""
    _check_scheme(url, (*SCHEMES, "data"))
    with _OPENER.open(url, timeout=timeout) as r:
        return r.read()

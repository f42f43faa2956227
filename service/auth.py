"""Bearer-token access control for the API, as a plain ASGI middleware.

With API tokens configured (``SARSHIP_TOKENS``), requests that change state (anything but
GET/HEAD/OPTIONS), and with ``protect_reads`` every request, need ``Authorization: Bearer
TOKEN``: ``401`` (with ``WWW-Authenticate: Bearer``) without one, ``403`` with a wrong one;
both are problem documents. The probes and metrics (``open_paths``) stay open.

A plain ASGI class rather than ``@app.middleware("http")``: Starlette's function middleware
wraps every request and response in extra tasks and streams, which under status polling cost
about a third of the server's CPU time per request (measured with bench/bench_service_load.py).
"""

from __future__ import annotations

import hmac

from starlette.types import ASGIApp, Receive, Scope, Send

from sarship.service.common import problem


class BearerAuth:
    def __init__(self, app: ASGIApp, tokens: list[str], protect_reads: bool = False, open_paths: tuple[str, ...] = ()):
        self.app = app
        self.tokens = [t.encode() for t in tokens]
        self.protect_reads = protect_reads
        self.open_paths = open_paths

    def _needs_token(self, scope: Scope) -> bool:
        return (
            scope["type"] == "http"
            and bool(self.tokens)
            and scope["path"] not in self.open_paths
            and (self.protect_reads or scope["method"] not in ("GET", "HEAD", "OPTIONS"))
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not self._needs_token(scope):
            await self.app(scope, receive, send)
            return
        auth = b""
        for k, v in scope.get("headers", ()):
            if k == b"authorization":
                auth = v
                break
        if not auth.lower().startswith(b"bearer "):
            r = problem(401, "unauthorized", "this request needs 'Authorization: Bearer TOKEN'")
            r.headers["WWW-Authenticate"] = "Bearer"
            await r(scope, receive, send)
            return
        tok = auth[7:].strip()  # bytes: compare_digest refuses non-ASCII str (a 500 otherwise)
        if not any(hmac.compare_digest(tok, t) for t in self.tokens):
            await problem(403, "forbidden", "the token is not valid")(scope, receive, send)
            return
        await self.app(scope, receive, send)

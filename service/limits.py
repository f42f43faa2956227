"""Request limits applied before a route runs, as a plain ASGI middleware (like
:mod:`sarship.service.auth`, see there why not Starlette's function middleware).

- The body of every request but an upload (``POST /scenes`` and ``POST /ais``, which stream to
  disk under their own limits, ``max_upload_mb`` and ``max_ais_upload_mb``) is at most ``max_body_kb``: a larger ``Content-Length``
  is a ``413`` problem at once, and a body without one (chunked) is counted as it arrives and
  refused with ``413`` as soon as it passes the limit, before any of it is parsed. The body
  read here is handed to the route unchanged.
- A path with a NUL character (``/jobs/a%00b``) names nothing: ``400`` problem.
"""

from __future__ import annotations

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from sarship.service.common import problem

#: (method, path) of the routes that take large bodies under their own limit.
OWN_LIMIT = {("POST", "/scenes"), ("POST", "/scenes/"), ("POST", "/ais"), ("POST", "/ais/")}


class RequestLimits:
    def __init__(self, app: ASGIApp, max_body: int):
        self.app = app
        self.max_body = max_body

    def _too_large(self, n: int | None = None) -> JSONResponse:
        said = f"of {n} bytes " if n is not None else ""
        return problem(
            413, "too large", f"the request body {said}exceeds the limit of {self.max_body} bytes (setting max_body_kb)"
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if "\x00" in scope.get("path", ""):
            await problem(400, "bad request", "the path contains a NUL character")(scope, receive, send)
            return
        if (scope["method"], scope["path"]) in OWN_LIMIT:
            await self.app(scope, receive, send)
            return
        for k, v in scope.get("headers", ()):
            if k == b"content-length":
                if v.strip().isdigit() and int(v) > self.max_body:
                    await self._too_large(int(v))(scope, receive, send)
                    return
                break
        # read the body here, counting (a chunked body has no Content-Length), then replay it
        chunks: list[bytes] = []
        n = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client left: let the app see it
                chunks.clear()  # (nothing is replayed but this message: the partial body is freed)
                first = message
                break
            body = message.get("body", b"")
            n += len(body)
            if n > self.max_body:
                await self._too_large()(scope, receive, send)
                return
            chunks.append(body)
            if not message.get("more_body", False):
                first = {"type": "http.request", "body": b"".join(chunks), "more_body": False}
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return first
            return await receive()

        await self.app(scope, replay, send)

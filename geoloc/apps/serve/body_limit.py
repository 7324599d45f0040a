"""ASGI middleware: a request body over `max_bytes` gets 413 before it is read whole.

A declared Content-Length over the limit is refused without reading the body; a body sent without one (chunked)
is counted as it arrives and refused at the first chunk past the limit. The error is an HTTPException, so
FastAPI's form parsing passes it on (it turns other parsing errors into a 400) and the app's handler words it.
"""

from __future__ import annotations

from fastapi import HTTPException
from fastapi.responses import JSONResponse


class BodyTooLarge(HTTPException):
    def __init__(self, max_bytes: int):
        super().__init__(413, f"the request body is over this server's limit of {max_bytes:,} bytes (max_bytes): "
                              "send a smaller file (a JPEG of a street panorama is well under a few MB)")


class BodyLimit:
    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope["headers"]).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > self.max_bytes:
            return await self._refuse(scope, receive, send)
        received = 0
        response_started = False

        async def counted_receive():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
            return message

        async def watched_send(message):
            nonlocal response_started
            response_started = response_started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted_receive, watched_send)
        except BodyTooLarge:  # raised where no handler words it (outside FastAPI's body parsing)
            if response_started:
                raise
            await self._refuse(scope, receive, send)

    async def _refuse(self, scope, receive, send):
        error = BodyTooLarge(self.max_bytes)
        await JSONResponse({"detail": error.detail}, status_code=413)(scope, receive, send)

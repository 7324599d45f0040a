"""ASGI middleware: every response carries a Content-Security-Policy and frame protection.

A response that sets its own policy keeps it (the page's, geoloc/apps/serve/page.py); every other one, JSON answers,
tiles, /openapi.json and errors included, gets API_POLICY, which lets a browser run and load nothing from it and
frame it nowhere (X-Frame-Options DENY for browsers that predate frame-ancestors). FastAPI's /docs and /redoc, off
unless `geoloc serve api_docs=true`, load their scripts, styles and fonts from public CDNs; with them on, those two
pages get DOCS_POLICY, which allows those hosts and nothing else.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders

API_POLICY = "default-src 'none'; img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
DOCS_POLICY = ("default-src 'none'; script-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net; "
               "style-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net https://fonts.googleapis.com; "
               "font-src https://fonts.gstatic.com; img-src 'self' data: https://fastapi.tiangolo.com "
               "https://cdn.redoc.ly; connect-src 'self'; worker-src blob:; base-uri 'none'; form-action 'none'; "
               "frame-ancestors 'none'")
EVERY_RESPONSE = {"X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer"}


class SecurityHeaders:
    """`policies`: the Content-Security-Policy of the paths that need another than API_POLICY (the docs pages)."""

    def __init__(self, app, policies: dict[str, str] | None = None):
        self.app, self.policies = app, policies or {}

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        policy = self.policies.get(scope["path"], API_POLICY)

        async def headed(message):
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("Content-Security-Policy", policy)
                for key, value in EVERY_RESPONSE.items():
                    headers.setdefault(key, value)
            await send(message)

        await self.app(scope, receive, headed)

"""Browser hardening headers on every answer: what the supervisor page and /docs may load, and where.

Scripts and styles come from this origin only (no inline script; Swagger UI sets inline styles, hence
'unsafe-inline' for styles alone), crops are shown from blob: URLs the page fetched with its token, map tiles
come only from the origin of `[supervisor] map_tiles` when one is configured, and
no other site may frame the page (clickjacking a Reject button). `nosniff` makes a browser believe the
content type, which the service sets only for content it checked (a crop is served as image/jpeg only
when its header is a JPEG's).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:{tiles}; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)


def headers(tile_origin: str = "") -> list[tuple[bytes, bytes]]:
    """The headers; `tile_origin` (scheme://host[:port] of `[supervisor] map_tiles`) may serve map images."""
    policy = CONTENT_SECURITY_POLICY.format(tiles=f" {tile_origin}" if tile_origin else "")
    return [
        (b"content-security-policy", policy.encode()),
        (b"x-frame-options", b"DENY"),
        (b"x-content-type-options", b"nosniff"),
        (b"referrer-policy", b"no-referrer"),
    ]


class SecurityHeaders:
    def __init__(self, app: ASGIApp, tile_origin: str = "") -> None:
        self.app = app
        self.headers = headers(tile_origin)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                names = {name.lower() for name, _ in message.get("headers", [])}
                message["headers"] = [
                    *message.get("headers", []),
                    *(h for h in self.headers if h[0] not in names),
                ]
            await send(message)

        await self.app(scope, receive, with_headers)

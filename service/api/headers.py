"""Security headers on every answer: no MIME sniffing, no framing (clickjacking), no referrer; and
on the dashboard a Content-Security-Policy that allows only its own files, so an injected `<script>`
or `onerror=` in any text it shows cannot run (it has no inline script; charts set inline styles).
Pictures and videos it fetched with the token are shown through blob: URLs (img-src, media-src).
The API docs page (/docs) runs under the same policy: its scripts are served from this origin."""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

COMMON = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
]
DASHBOARD_CSP = (
    b"default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    b"img-src 'self' blob: data:; media-src 'self' blob:; connect-src 'self'; object-src 'none'; "
    b"base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)


class SecurityHeaders:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        extra = COMMON + (
            [(b"content-security-policy", DASHBOARD_CSP)]
            if scope["path"].startswith(("/dashboard", "/docs"))
            else []
        )

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": list(message.get("headers", [])) + extra}
            await send(message)

        await self.app(scope, receive, send_with_headers)

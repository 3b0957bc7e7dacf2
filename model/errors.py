"""The one root of every error this project raises on purpose, and its four kinds. The command
line (cli/main.py `EXIT_CODES`) and the API (service/api/app.py `STATUSES`) each map a kind to an
exit code or an HTTP status in one table, so a new error class picks its kind and is reported right
everywhere. Each kind also keeps the built-in base (ValueError, RuntimeError) code catches."""

from __future__ import annotations

from typing import ClassVar


class LecoError(Exception):
    kind: ClassVar[str] = "failed"


class InvalidInput(LecoError, ValueError):
    """The user can fix it: a bad request, a broken dataset, a wrong config. The message names what
    is wrong."""

    kind = "invalid"


class Conflict(LecoError, ValueError):
    """The request clashes with what exists (a name taken); nothing was changed."""

    kind = "conflict"


class Busy(LecoError, RuntimeError):
    """No capacity for this right now; the same request later may succeed."""

    kind = "busy"


class Unavailable(LecoError, RuntimeError):
    """Something this needs is away (the database, a worker process); retry later."""

    kind = "unavailable"


class Failed(LecoError, RuntimeError):
    """Work that could not be done, with the reason; not the request's fault."""

    kind = "failed"


KINDS = ("invalid", "conflict", "busy", "unavailable", "failed")

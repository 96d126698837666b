"""Typed errors of the HKTex client.

The service answers every failure with a 4xx/5xx and ``{"detail": ...}``; a caller should be
able to ``except NotFound`` rather than compare status codes, and still read the server's own
reason (``exc.reason``) because that is what tells a user how to fix the request.
"""

from __future__ import annotations

from typing import Any


class HKTexClientError(Exception):
    """Base of every error this package raises."""


class HKTexAPIError(HKTexClientError):
    """The service answered with an error status.

    ``status`` is the HTTP status, ``reason`` the server's explanation (its ``detail`` rendered
    as one line), ``detail`` the raw ``detail`` value (a string, or FastAPI's list of
    validation problems), ``method``/``url`` the request that failed.
    """

    def __init__(
        self,
        status: int,
        reason: str,
        detail: Any = None,
        method: str = "",
        url: str = "",
    ) -> None:
        self.status = status
        self.reason = reason
        self.detail = detail if detail is not None else reason
        self.method = method
        self.url = url
        super().__init__(f"{status} {method} {url}: {reason}".replace("  ", " "))


class BadRequest(HKTexAPIError):
    """400: the request is malformed in a way the server could name."""


class Unauthorized(HKTexAPIError):
    """401/403: no token, an unknown token, or a token not allowed to do this."""


class NotFound(HKTexAPIError):
    """404: no such record, or it belongs to another owner (the service does not say which)."""


class Conflict(HKTexAPIError):
    """409: the record is not in a state that allows this (e.g. a job not yet finished)."""


class PayloadTooLarge(HKTexAPIError):
    """413: the upload or query exceeds the service's configured limits."""


class UnsupportedMediaType(HKTexAPIError):
    """415: a body or ``Accept`` type the route does not speak."""


class ValidationFailed(HKTexAPIError):
    """422: the body parsed but its content is invalid (bad mesh, bad config, bad query)."""


class ServerError(HKTexAPIError):
    """5xx: the service failed; a bug or an overloaded machine, never the caller's fault."""


class JobFailed(HKTexClientError):
    """A job this client waited for ended ``failed`` or ``cancelled``."""

    def __init__(self, job: Any) -> None:
        self.job = job
        state = getattr(job, "state", "?")
        error = getattr(job, "error", None)
        super().__init__(
            f"job {getattr(job, 'id', '?')} ended {state}: {error or 'no reason given'}"
        )


class WaitTimeout(HKTexClientError, TimeoutError):
    """``wait`` gave up before the job reached a final state; the job keeps running."""

    def __init__(self, job: Any, timeout: float) -> None:
        self.job = job
        super().__init__(
            f"job {getattr(job, 'id', '?')} still {getattr(job, 'state', '?')} after {timeout:g} s"
        )


_BY_STATUS: dict[int, type[HKTexAPIError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Unauthorized,
    404: NotFound,
    409: Conflict,
    413: PayloadTooLarge,
    415: UnsupportedMediaType,
    422: ValidationFailed,
}


def _reason_of(detail: Any) -> str:
    """One readable line from a ``detail`` (a string, or FastAPI's list of problems)."""
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list):
        parts = []
        for item in detail:
            if isinstance(item, dict):
                loc = ".".join(str(p) for p in item.get("loc", ()) if p != "body")
                msg = item.get("msg", "")
                parts.append(f"{loc}: {msg}" if loc else str(msg))
            else:
                parts.append(str(item))
        return "; ".join(parts)
    if isinstance(detail, dict):
        return str(detail.get("message") or detail.get("reason") or detail)
    return str(detail)


def error_for(
    status: int, body: Any, method: str = "", url: str = "", text: str = ""
) -> HKTexAPIError:
    """The typed error for an error response (``body`` is its parsed JSON, or None)."""
    detail = body.get("detail") if isinstance(body, dict) and "detail" in body else None
    reason = _reason_of(detail) if detail is not None else (text.strip()[:500] or f"HTTP {status}")
    cls = _BY_STATUS.get(status)
    if cls is None:
        cls = ServerError if status >= 500 else HKTexAPIError
    return cls(status, reason, detail, method, url)

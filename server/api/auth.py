"""Bearer tokens mapping to owners.

With no tokens configured the server only listens on loopback (``Settings.check_bind``) and
every request belongs to the single owner ``local``. With tokens, a request without a valid
one is a 401; tokens are compared in constant time.
"""

from __future__ import annotations

import hmac

from fastapi import HTTPException, Request, status
from hktex_server.settings import LOCAL_OWNER


def owner_for(authorization: str | None, tokens: dict[str, str]) -> str:
    """The owner a request's ``Authorization`` header names; raises 401 when it names none."""
    if not tokens:
        return LOCAL_OWNER
    scheme, _, token = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise _unauthorised("missing bearer token")
    token = token.strip()
    owner = None
    for known, who in tokens.items():  # scan all: no early exit leaking which prefix matched
        if hmac.compare_digest(known.encode(), token.encode()):
            owner = who
    if owner is None:
        raise _unauthorised("invalid token")
    return owner


def current_owner(request: Request) -> str:
    """FastAPI dependency: the owner of this request."""
    return owner_for(request.headers.get("authorization"), request.app.state.tokens)


def _unauthorised(reason: str) -> HTTPException:
    return HTTPException(
        status.HTTP_401_UNAUTHORIZED, detail=reason, headers={"WWW-Authenticate": "Bearer"}
    )

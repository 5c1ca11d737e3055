"""FastAPI dependencies: the services, a database session, the operator behind a change."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from backend.auth import token_matches
from backend.services import Services

_bearer = HTTPBearer(auto_error=False, description="the token of MOSAIC_API_TOKEN")


async def get_services(request: Request) -> Services:  # async: no thread hop to get it
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(get_services)]


def get_session(services: ServicesDep) -> Iterator[Session]:
    with services.sessions() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]


#: What a change without the token is told (HTTP 401).
UNAUTHORISED = (
    "this changes the instrument or its data: send 'Authorization: Bearer <token>' with the "
    "server's API token (MOSAIC_API_TOKEN, or the file api_token in the data dir)"
)


def bearer_matches(header: str | None, token: str) -> bool:
    """Whether an ``Authorization`` header carries ``token`` as its bearer token."""
    scheme, _, given = (header or "").partition(" ")
    return scheme.lower() == "bearer" and token_matches(given.strip(), token)


def require_operator(
    services: ServicesDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    x_operator: Annotated[str | None, Header(max_length=100)] = None,
) -> str:
    """Who asks for a change: the bearer token must match; ``X-Operator`` names the person."""
    if credentials is None or not token_matches(credentials.credentials, services.token):
        raise HTTPException(
            status_code=401, detail=UNAUTHORISED, headers={"WWW-Authenticate": "Bearer"}
        )
    return (x_operator or "").strip() or "api"


OperatorDep = Annotated[str, Depends(require_operator)]

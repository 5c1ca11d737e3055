"""FastAPI dependencies: the services, a database session, who asks (the principal the
request gate found, :mod:`backend.api.access`)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from sqlalchemy.orm import Session

from backend.security.authority import Principal
from backend.services import Services


async def get_services(request: Request) -> Services:  # async: no thread hop to get it
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(get_services)]


def get_session(services: ServicesDep) -> Iterator[Session]:
    with services.sessions() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]


async def get_principal(request: Request) -> Principal:
    """Who asks: put on the request by the gate, which refused it already if nobody may."""
    who: Principal | None = getattr(request.state, "principal", None)
    if who is None:
        raise HTTPException(401, "who asks is not known", headers={"WWW-Authenticate": "Bearer"})
    return who


PrincipalDep = Annotated[Principal, Depends(get_principal)]


async def require_operator(who: PrincipalDep) -> str:
    """The name of who asks for a change (a user's name; in the single-user mode the name
    ``X-Operator`` gives, or ``api``)."""
    return who.name


OperatorDep = Annotated[str, Depends(require_operator)]

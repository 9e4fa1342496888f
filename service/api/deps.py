"""FastAPI dependencies: the process's :class:`~service.app.services.Services`, a database
session per request, the settings, and the job submitter.

Nothing here reads the environment: ``create_app(settings)`` puts the services on
``app.state`` and every route gets them through these functions, so a test builds an app on
a temporary directory and overrides what it needs (``app.dependency_overrides``).

The dependencies that only read ``app.state`` are ``async def``: FastAPI runs a plain
``def`` dependency in its thread pool, one thread hand-off (and back) per dependency and
request, which on a loaded 2-core machine cost more than the work (issue 23). Only
:func:`get_session`, which may wait on the database, stays a thread-pool function.
"""

from __future__ import annotations

from typing import Annotated, Iterator

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from service.app.services import Services, Submit
from service.config import Settings


async def get_services(request: Request) -> Services:
    """The app's :class:`Services` (opened by the lifespan)."""
    return request.app.state.services


async def get_settings(services: Annotated[Services, Depends(get_services)]) -> Settings:
    """The app's settings."""
    return services.settings


def get_session(services: Annotated[Services, Depends(get_services)]) -> Iterator[Session]:
    """A database session for one request, closed after the response."""
    with services.session() as session:
        yield session


async def get_submit(services: Annotated[Services, Depends(get_services)]) -> Submit:
    """The job submitter: :func:`service.jobs.queue.submit` with the app's settings."""
    from service.jobs import queue

    settings = services.settings
    return lambda job_id: queue.submit(settings, job_id)


ServicesDep = Annotated[Services, Depends(get_services)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]
SubmitDep = Annotated[Submit, Depends(get_submit)]

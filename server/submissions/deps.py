"""What the submissions' routes use of the app's services (built in server/services.py): the
plumbing every route has, the image resolver and the outbox's dispatcher."""

from __future__ import annotations

from typing import Protocol

from fastapi import Request

from server.kit.deps import Plumbing
from server.submissions.outbox import Dispatcher
from server.submissions.service import Resolver


class SubmissionServices(Plumbing, Protocol):
    resolve: Resolver
    dispatcher: Dispatcher


def services(request: Request) -> SubmissionServices:
    found: SubmissionServices = request.app.state.services
    return found

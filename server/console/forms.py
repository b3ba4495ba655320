"""How every console form acts: do the change and commit, then back to its page with a notice;
on a refusal, roll back and show the page again with the problem by the form that caused it."""

from __future__ import annotations

from collections.abc import Callable
from urllib.parse import urlencode

from fastapi import Response
from sqlalchemy.orm import Session as DB

from server.kit.errors import AppError
from server.kit.pages import redirect


def act_and_return(
    db: DB,
    act: Callable[[], object],
    *,
    page: str,
    done: str,
    refused: Callable[[AppError], Response],
) -> Response:
    """Run `act` and commit, then redirect to `page` saying `done`; `refused(error)` is the
    answer when the change is refused."""
    try:
        act()
        db.commit()
    except AppError as exc:
        db.rollback()
        return refused(exc)
    return redirect(f"{page}?{urlencode({'done': done})}")

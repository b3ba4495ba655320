"""Tracks: challenges grouped under a head challenge (a suite each, or one suite with other
observation modes and conditions), each with its own phases, boards and submit choice; the
head says whether the group's submissions count against one quota (docs/server.md, Tracks)."""

from __future__ import annotations

import re

from sqlalchemy import select
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import selectinload

from server.kit.errors import Invalid, NotFound
from server.models import Challenge

TRACK_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")


def track_name(challenge: Challenge) -> str:
    """The challenge's name within its group: its `track`, else its slug."""
    return challenge.track or challenge.slug


def head_of(db: DB, challenge: Challenge) -> Challenge:
    """The head of the challenge's group: itself, unless it is a track of another (a track
    whose head is gone stands alone)."""
    if challenge.track_of is None:
        return challenge
    return db.get(Challenge, challenge.track_of) or challenge


def tracks_of(db: DB, challenge: Challenge) -> list[Challenge]:
    """The challenges of its group with their phases, the head first, then the tracks in the
    order they were added; a challenge alone is its only track."""
    head = head_of(db, challenge)
    found = db.scalars(
        select(Challenge)
        .options(selectinload(Challenge.phases))
        .where((Challenge.id == head.id) | (Challenge.track_of == head.id))
        .order_by((Challenge.id != head.id), Challenge.id)
    ).all()
    return list(found) or [challenge]


def get_track(db: DB, challenge: Challenge, name: str | None) -> Challenge:
    """The track of the challenge's group named `name` (its track name or slug); None: the
    challenge itself. Invalid naming the group's tracks otherwise."""
    if name is None or name in ("", challenge.slug, challenge.track):
        return challenge
    group = tracks_of(db, challenge)
    for track in group:
        if name in (track.slug, track.track):
            return track
    names = ", ".join(track_name(t) for t in group)
    raise Invalid(
        f"challenge {challenge.slug!r} has no track {name!r} (it has: {names})",
        fields={"track": f"one of: {names}"},
    )


def quota_group(db: DB, challenge: Challenge) -> tuple[Challenge, list[int]]:
    """Whose quota a submission to `challenge` draws on, and the challenges whose submissions
    count against it: the head's and the whole group's when the head shares it, else the
    challenge's own."""
    head = head_of(db, challenge)
    if not head.quota_shared:
        return challenge, [challenge.id]
    return head, [t.id for t in tracks_of(db, head)]


def join_group(
    db: DB,
    challenge: Challenge,
    *,
    track: str | None,
    track_of: str | None,
    quota_shared: bool | None,
) -> None:
    """Apply `challenge load`'s track options: name the challenge's track, make it a track of
    the challenge `track_of`, and set whether its group shares one quota."""
    if track is not None:
        if not TRACK_NAME.match(track):
            raise Invalid(f"track name {track!r}: lowercase letters, digits, - and _, at most 32")
        challenge.track = track
    if track_of is not None:
        head = db.scalar(select(Challenge).where(Challenge.slug == track_of))
        if head is None:
            raise NotFound(f"no challenge {track_of!r} to be a track of; load it first")
        if head.slug == challenge.slug or head.track_of is not None:
            raise Invalid(
                f"{track_of!r} cannot head a group of tracks: name a challenge that is no "
                "track itself, and not this one"
            )
        if challenge.id is not None and db.scalar(
            select(Challenge.id).where(Challenge.track_of == challenge.id).limit(1)
        ):
            raise Invalid(f"{challenge.slug!r} heads tracks of its own: it cannot be a track")
        challenge.track_of = head.id
    db.flush()
    group = tracks_of(db, challenge)
    names = [track_name(t) for t in group]
    if len(set(names)) != len(names):
        raise Invalid(f"two tracks of {group[0].slug!r} share a name: {', '.join(names)}")
    if quota_shared is not None:
        head_of(db, challenge).quota_shared = quota_shared

"""`manieval submit --track`: the client names the track in the submission it sends, and only
when one is chosen (a server from before tracks refuses the field)."""

from __future__ import annotations

import json

import httpx
from typer.testing import CliRunner

from manieval.cli import app
from manieval.client import Client


def _sent(track: str | None) -> dict[str, object]:
    bodies: list[dict[str, object]] = []

    def answer(request: httpx.Request) -> httpx.Response:
        bodies.append(json.loads(request.content))
        return httpx.Response(202, json={"id": 1})

    with Client("http://127.0.0.1:1", token="t", transport=httpx.MockTransport(answer)) as client:
        client.submit(
            challenge="maniskill-core",
            phase="dev",
            image="x",
            description="",
            public=True,
            track=track,
        )
    return bodies[0]


def test_the_submission_names_the_chosen_track() -> None:
    assert _sent("visual")["track"] == "visual"
    assert "track" not in _sent(None)


def test_submit_takes_a_track() -> None:
    r = CliRunner().invoke(app, ["submit", "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "--track" in r.output

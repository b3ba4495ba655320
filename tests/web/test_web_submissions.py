"""A submission's page: who sees what (404 as the API), results, failures, videos, actions."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update
from sqlalchemy.orm import Session

from evaluator.results import Abort, Video
from server.kit.settings import Settings
from server.models import Challenge, EpisodeResultRow, State, Submission
from testkit.factories import RecordingQueue, make_user
from tests.web.helpers import browser, csrf_of, finished

SECRET = "PRIVATE-LOG-LINE-7c1"


@pytest.fixture
def people(client: TestClient, db: Session) -> dict[str, TestClient]:
    for name in ("alice", "bob"):
        make_user(db, name)
    make_user(db, "judge", admin=True)
    return {name: browser(client, name) for name in ("alice", "bob", "judge")} | {
        "anonymous": browser(client)
    }


def alice_s(db: Session, challenge: Challenge, **options: object) -> Submission:
    from server.models import User

    alice = db.query(User).filter_by(username="alice").one()
    return finished(db, alice, challenge, [True, False], log_tail=SECRET, **options)  # type: ignore[arg-type]


def test_private_and_hidden_submissions_are_404_to_others_like_the_api(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, TestClient]
) -> None:
    private = alice_s(db, tiny, public=False)
    hidden = alice_s(db, tiny)
    hidden.hidden = True
    db.commit()
    for s in (private, hidden):
        for path in ("", "/outcome", "/events"):
            for who in ("bob", "anonymous"):
                r = people[who].get(f"/submissions/{s.id}{path}")
                assert r.status_code == 404, (who, path)
                assert SECRET not in r.text
            api = client.get(f"/api/v1/submissions/{s.id}")
            assert api.status_code == 404
        assert people["alice"].get(f"/submissions/{s.id}").status_code == 200
        assert people["judge"].get(f"/submissions/{s.id}").status_code == 200


def test_results_show_intervals_and_the_log_and_episodes_only_to_owner_and_admins(
    db: Session, tiny: Challenge, people: dict[str, TestClient]
) -> None:
    s = alice_s(db, tiny, description="two tries")
    public_view = people["bob"].get(f"/submissions/{s.id}").text
    assert "Results" in public_view
    assert 'class="ibar"' in public_view
    assert "Success rate per task, with 95% intervals" in public_view  # the chart
    assert "nominal</strong> 0.500" in public_view
    assert SECRET not in public_view
    assert "episodes-heading" not in public_view
    for who in ("alice", "judge"):
        html = people[who].get(f"/submissions/{s.id}").text
        assert SECRET in html
        assert html.count("<tr><td>nominal</td><td>PickCube-v1</td>") == 2  # the episodes
        assert ">1000</td>" in html  # public-phase seeds are shown


def test_a_failed_submission_says_why(
    db: Session, tiny: Challenge, people: dict[str, TestClient]
) -> None:
    s = alice_s(db, tiny, state=State.FAILED, reason="the policy exited with exit code 3")
    html = people["bob"].get(f"/submissions/{s.id}").text
    assert "Why it ended failed" in html
    assert "the policy exited with exit code 3" in html
    assert SECRET not in html


def test_a_submission_that_ended_part_way_shows_the_episodes_that_ran_and_no_others(
    db: Session, tiny: Challenge, people: dict[str, TestClient]
) -> None:
    crash = Abort(kind="policy_crashed", reason="the policy closed the connection")
    s = alice_s(db, tiny, state=State.FAILED, reason=crash.reason, planned=3, abort=crash)
    for who in ("alice", "bob"):
        html = people[who].get(f"/submissions/{s.id}").text
        assert "What ran before it ended" in html
        assert "4 of the 6 planned episodes ran before it ended" in html  # 2 conditions
        assert "2 of 3" in html  # per task and condition
        assert 'class="ibar"' not in html  # no interval over episodes that never started
        assert "0.500" not in html
        assert "0.333" not in html
    owner = people["alice"].get(f"/submissions/{s.id}").text
    assert "4 episodes</caption>" in owner  # the ones that ran, and no others
    assert "the evaluation stopped before it" not in owner
    assert "The log below shows its last words" in owner
    public = people["bob"].get(f"/submissions/{s.id}").text
    assert "Its owner can read the policy's log" in public
    assert "The log below" not in public


def test_a_submission_whose_policy_never_connected_says_no_episode_ran(
    db: Session, tiny: Challenge, people: dict[str, TestClient], client: TestClient
) -> None:
    never = Abort(kind="policy_crashed", reason="the policy exited before connecting")
    from server.models import User

    alice = db.query(User).filter_by(username="alice").one()
    s = finished(
        db, alice, tiny, [], state=State.FAILED, reason=never.reason, planned=3, abort=never
    )
    html = people["alice"].get(f"/submissions/{s.id}").text
    assert "No episodes ran: it ended before its first episode." in html
    assert "Mean steps" not in html
    assert 'class="ibar"' not in html
    body = client.get(f"/api/v1/submissions/{s.id}").json()
    assert [(t["episodes"], t["episodes_ran"], t["success_rate"]) for t in body["tasks"]] == [
        (3, 0, None)
    ] * 2
    assert [t["mean_steps"] for t in body["tasks"]] == [None, None]
    assert body["conditions"] == {}


def test_stored_videos_of_the_current_attempt_are_shown_to_whoever_sees_the_submission(
    db: Session, tiny: Challenge, people: dict[str, TestClient], settings: Settings
) -> None:
    from server.models import User

    alice = db.query(User).filter_by(username="alice").one()
    videos = [  # the worker's paths mean nothing to the server: it looks names up itself
        Video(env_id="PickCube-v1", condition="nominal", episode=0, path="/etc/hostname"),
        Video(env_id="PickCube-v1", condition="nominal", episode=1, path="/etc/hostname"),
    ]
    s = finished(db, alice, tiny, [True, False], videos=videos, public=False)
    clip = settings.data_dir / "videos" / str(s.id) / "1" / "nominal--PickCube-v1--ep0.mp4"
    clip.parent.mkdir(parents=True)
    clip.write_bytes(b"\x00\x00\x00\x18ftypmp42")  # episode 1 was listed, never stored
    url = f"/api/v1/submissions/{s.id}/videos/nominal--PickCube-v1--ep0.mp4"
    html = people["alice"].get(f"/submissions/{s.id}").text
    assert html.count("<video ") == 1
    assert f'src="{url}"' in html
    assert "PickCube-v1</strong>, nominal, episode 0" in html
    r = people["alice"].get(url)
    assert r.status_code == 200
    assert r.headers["content-type"] == "video/mp4"
    assert people["alice"].get(url.replace("ep0", "ep1")).status_code == 404
    for who in ("bob", "anonymous"):
        assert people[who].get(url).status_code == 404
    s.public = True
    db.commit()
    assert people["bob"].get(url).status_code == 200
    assert f'src="{url}"' in people["anonymous"].get(f"/submissions/{s.id}").text


def act(client: TestClient, s: Submission, action: str, **fields: str) -> int:
    page = client.get(f"/submissions/{s.id}").text
    token = csrf_of(page) if "csrf_token" in page else ""
    return client.post(
        f"/submissions/{s.id}/{action}", data={"csrf_token": token, **fields}
    ).status_code


def test_only_admins_rerun_hide_and_flag_baselines(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    work: RecordingQueue,
) -> None:
    s = alice_s(db, tiny)
    owner_page = people["alice"].get(f"/submissions/{s.id}").text
    assert "Re-run" not in owner_page
    assert "Flag as baseline" not in owner_page
    for action, fields in (
        ("rerun", {}),
        ("hidden", {"hidden": "true"}),
        ("baseline", {"baseline": "true"}),
    ):
        assert act(people["alice"], s, action, **fields) == 403
        assert act(people["bob"], s, action, **fields) == 403
    admin_page = people["judge"].get(f"/submissions/{s.id}").text
    assert "Re-run" in admin_page
    assert "Flag as baseline" in admin_page
    assert "Hide" in admin_page
    board = "/challenges/server-tiny/leaderboard?phase=dev"
    assert act(people["judge"], s, "baseline", baseline="true") == 303
    assert '<span class="badge">baseline</span>' in client.get(board).text
    assert act(people["judge"], s, "hidden", hidden="true") == 422  # say why
    assert act(people["judge"], s, "hidden", hidden="true", reason="a copy of #1") == 303
    assert f"/submissions/{s.id}" not in client.get(board).text
    assert people["bob"].get(f"/submissions/{s.id}").status_code == 404
    assert act(people["judge"], s, "rerun") == 303
    db.refresh(s)
    assert (s.state, s.attempt) == (State.QUEUED, 2)
    assert work.sent[-1] == (s.id, 2)
    assert act(people["judge"], s, "rerun") == 409  # it has not ended


def test_the_owner_cancels_and_changes_visibility(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, TestClient]
) -> None:
    from server.models import User
    from testkit.factories import queue_submission

    alice = db.query(User).filter_by(username="alice").one()
    s = queue_submission(db, alice, tiny)
    db.commit()
    assert act(people["bob"], s, "cancel") == 404
    assert act(people["alice"], s, "visibility", public="false") == 303
    assert people["bob"].get(f"/submissions/{s.id}").status_code == 404
    assert act(people["alice"], s, "cancel") == 303
    db.refresh(s)
    assert s.state == State.CANCELLED
    assert not s.public
    assert "cancelled by its owner" in people["alice"].get(f"/submissions/{s.id}").text


def test_the_at_end_column_shows_only_where_the_suite_measures_it_and_says_what_it_is(
    db: Session, tiny: Challenge, people: dict[str, TestClient]
) -> None:
    s = alice_s(db, tiny)  # episodes that ran to their step limit: both measured
    measured = people["alice"].get(f"/submissions/{s.id}").text
    assert '<th scope="col" title="Still solved at the last step">At end</th>' in measured
    assert "<em>At end</em>: still solved at the last step" in measured
    # A suite that stops an episode at its first success measures nothing at the end.
    db.execute(update(EpisodeResultRow).values(success_at_end=None))
    db.commit()
    unmeasured = people["alice"].get(f"/submissions/{s.id}").text
    assert "At end" not in unmeasured
    assert "success at the last step is not measured" in unmeasured
    assert "n/a" not in unmeasured

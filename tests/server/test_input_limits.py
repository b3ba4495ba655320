"""No input reaches a 500 (issue 13): characters Postgres or the pages cannot hold in every text
input of the API and of the forms (enumerated from the OpenAPI document and the page routers,
so new routes are covered by themselves), bodies refused before parsing, strict booleans,
`Allow` on every 405, `next=` outside Latin-1, login throttling that cannot lock an owner out,
and weak passwords refused with zxcvbn's reasons.

Every test using `client` runs on SQLite and on this machine's Postgres.
"""

from __future__ import annotations

import json
import re
import select
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server.accounts import service as accounts
from server.kit.db import ROOT
from server.kit.settings import Settings
from testkit.factories import PASSWORD, make_challenge, make_user, queue_submission, token_for
from tests.web.helpers import browser, csrf_of

API = "/api/v1"
# NUL, other C0 controls, the non-characters: refused everywhere (422).
BAD_TEXT = ["a\x00b", "a\x01b", "a\x1bb", "a\ufffeb", "a\uffffb"]
# A lone surrogate can only come in through JSON escapes.
LONE_SURROGATE = "a\ud800b"
OPENAPI_METHODS = ("get", "post", "put", "patch", "delete")


@pytest.fixture
def world(client: TestClient, db: Session) -> dict[str, Any]:
    """Alice with a challenge, a submission and a token; her API headers."""
    alice = make_user(db, "alice")
    challenge = make_challenge(db, quota_per_day=100, quota_concurrent=100)
    submission = queue_submission(db, alice, challenge)
    db.commit()
    token, _ = accounts.create_token(db, user=alice, name="laptop")
    db.commit()
    return {
        "headers": token_for(client, "alice"),
        "slug": challenge.slug,
        "submission": submission.id,
        "token": token.id,
    }


def _operations(client: TestClient) -> Iterator[tuple[str, str, dict[str, Any]]]:
    doc = client.get("/openapi.json").json()
    for path, item in doc["paths"].items():
        for method in OPENAPI_METHODS:
            if method in item:
                yield method, path, item[method]


def _fill(path: str, world: dict[str, Any], **override: str) -> str:
    values = {
        "slug": world["slug"],
        "submission_id": str(world["submission"]),
        "token_id": str(world["token"]),
    }
    values.update(override)
    return re.sub(r"\{(\w+)\}", lambda m: values.get(m[1], "1"), path)


def _json_fields(operation: dict[str, Any], doc: dict[str, Any]) -> dict[str, Any]:
    content = operation.get("requestBody", {}).get("content", {})
    schema = content.get("application/json", {}).get("schema")
    if schema is None:
        return {}
    if "$ref" in schema:
        schema = doc["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    return dict(schema.get("properties", {}))


def _is_text(field: dict[str, Any]) -> bool:
    return any(v.get("type") == "string" for v in field.get("anyOf", [field]))


def test_every_json_text_field_refuses_unstorable_characters(
    client: TestClient, world: dict[str, Any]
) -> None:
    doc = client.get("/openapi.json").json()
    checked = 0
    for method, path, operation in _operations(client):
        for name, field in _json_fields(operation, doc).items():
            if not _is_text(field):
                continue
            for bad in [*BAD_TEXT, LONE_SURROGATE]:
                r = client.request(
                    method,
                    _fill(path, world),
                    content=json.dumps({name: bad}),  # ASCII: the surrogate as an escape
                    headers={**world["headers"], "Content-Type": "application/json"},
                )
                assert r.status_code == 422, (method, path, name, bad, r.text)
                assert name in r.json()["error"]["fields"], (method, path, name, r.text)
                checked += 1
    assert checked >= 10 * (len(BAD_TEXT) + 1)  # users, session, tokens, submissions...


def test_every_json_text_field_documents_what_it_refuses(client: TestClient) -> None:
    doc = client.get("/openapi.json").json()
    for method, path, operation in _operations(client):
        for name, field in _json_fields(operation, doc).items():
            for variant in field.get("anyOf", [field]):
                if variant.get("type") == "string":
                    assert "pattern" in variant, (method, path, name)
                    assert "maxLength" in variant, (method, path, name)


def test_the_registration_body_states_its_rules(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()["components"]["schemas"]["RegisterIn"]
    props = schema["properties"]
    assert props["username"]["pattern"] == "^[A-Za-z0-9]+(?:(?:_|__|-+)[A-Za-z0-9]+)*$"
    assert (props["username"]["minLength"], props["username"]["maxLength"]) == (3, 32)
    assert props["email"]["format"] == "email"
    assert props["password"]["minLength"] == 10


@pytest.mark.parametrize("bad", ["%00", "%01", "%1B", "%EF%BF%BE", "%0A"])
def test_every_path_and_query_parameter_refuses_unstorable_characters(
    client: TestClient, world: dict[str, Any], bad: str
) -> None:
    for method, path, operation in _operations(client):
        for param in operation.get("parameters", []):
            if param["in"] == "path":
                url = _fill(path, world, **{param["name"]: bad})
            elif param["in"] == "query":
                url = f"{_fill(path, world)}?{param['name']}={bad}"
            else:
                continue
            r = client.request(method, url, headers=world["headers"])
            assert r.status_code == 422, (method, url, r.text)
            assert r.json()["error"]["code"] == "invalid"


def test_a_lone_surrogate_in_a_url_is_never_a_500(
    client: TestClient, world: dict[str, Any]
) -> None:
    # Percent-decoding replaces what is not UTF-8, so the server sees U+FFFD: an unknown name.
    for url in (f"{API}/challenges/%ED%A0%80", f"{API}/submissions?challenge=%ED%A0%80"):
        r = client.get(url, headers=world["headers"])
        assert 400 <= r.status_code < 500, (url, r.text)


@pytest.mark.parametrize(
    "url", ["/challenges/%00", "/login?next=%00", "/challenges/x%01/leaderboard", "/%00"]
)
def test_pages_answer_an_unstorable_url_with_an_error_page(client: TestClient, url: str) -> None:
    r = client.get(url)
    assert r.status_code == 422
    assert r.headers["content-type"].startswith("text/html")
    assert "not allowed" in r.text


def _form_routes(client: TestClient) -> Iterator[tuple[str, list[str]]]:
    app: Any = client.app
    for router in app.state.page_routers:
        for route in router.routes:
            if isinstance(route, APIRoute) and "POST" in route.methods:
                fields = [f for f in _form_fields(route.dependant) if f != "csrf_token"]
                yield route.path, sorted(set(fields))


def _form_fields(dependant: Dependant) -> list[str]:
    """The form fields a route reads, its dependencies' included."""
    names = [param.alias for param in dependant.body_params]
    for sub in dependant.dependencies:
        names += _form_fields(sub)
    return names


def test_every_form_field_refuses_unstorable_characters(
    client: TestClient, world: dict[str, Any]
) -> None:
    alice = browser(client, "alice")
    token = csrf_of(alice.get("/account").text)
    routes = list(_form_routes(client))
    assert {"/login", "/register", "/account/tokens"} <= {path for path, _ in routes}
    checked = 0
    for path, fields in routes:
        for name in fields:
            for bad in BAD_TEXT:
                r = alice.post(_fill(path, world), data={"csrf_token": token, name: bad})
                assert r.status_code == 422, (path, name, bad, r.status_code)
                assert "cannot be stored" in r.text, (path, name)
                checked += 1
    assert checked >= 8 * len(BAD_TEXT)


def test_the_login_form_refuses_a_nul_before_looking_up_the_account(client: TestClient) -> None:
    visitor = browser(client)
    token = csrf_of(visitor.get("/login").text)
    r = visitor.post("/login", data={"csrf_token": token, "login": "bob\x00", "password": "x"})
    assert r.status_code == 422
    assert "login" in r.text


def test_multiline_text_keeps_its_newlines_and_one_line_fields_refuse_them(
    client: TestClient, world: dict[str, Any]
) -> None:
    url = f"{API}/submissions/{world['submission']}"
    r = client.patch(url, json={"description": "line one\r\n\tline two"}, headers=world["headers"])
    assert r.status_code == 200, r.text
    assert r.json()["description"] == "line one\r\n\tline two"
    r = client.post(f"{API}/tokens", json={"name": "two\nlines"}, headers=world["headers"])
    assert r.status_code == 422
    assert "name" in r.json()["error"]["fields"]


@pytest.mark.parametrize("value", [0, 1, "false", "true", None, []])
def test_booleans_are_strict(client: TestClient, world: dict[str, Any], value: object) -> None:
    url = f"{API}/submissions/{world['submission']}"
    r = client.patch(url, json={"public": value}, headers=world["headers"])
    if value is None:
        assert r.status_code == 200  # "leave it as it is"
    else:
        assert r.status_code == 422, r.text
        assert "public" in r.json()["error"]["fields"]


def test_every_405_lists_every_method_of_its_path(
    client: TestClient, world: dict[str, Any]
) -> None:
    for path, item in client.get("/openapi.json").json()["paths"].items():
        documented = {method.upper() for method in item if method in OPENAPI_METHODS}
        for method in {"GET", "POST", "PUT", "PATCH", "DELETE"} - documented:
            r = client.request(method, _fill(path, world), headers=world["headers"])
            assert r.status_code == 405, (method, path)
            assert set(r.headers["Allow"].split(", ")) == documented, (method, path)
    r = client.put("/login")
    assert r.status_code == 405
    assert set(r.headers["Allow"].split(", ")) == {"GET", "POST"}


# --- Bodies ------------------------------------------------------------------------------------


def test_a_declared_large_body_is_refused_before_csrf_or_authentication(
    client: TestClient,
) -> None:
    big = b"x" * (64 * 1024 + 1)
    for path, ctype in [
        (f"{API}/users", "application/json"),
        (f"{API}/tokens", "application/json"),  # needs a login: 413 comes first
        ("/login", "application/x-www-form-urlencoded"),  # needs a CSRF token: 413 first
        ("/account/tokens", "application/x-www-form-urlencoded"),
    ]:
        r = client.post(path, content=big, headers={"Content-Type": ctype})
        assert r.status_code == 413, (path, r.text)
    r = client.post(f"{API}/users", content=big, headers={"Content-Type": "application/json"})
    assert r.json()["error"]["code"] == "too_large"
    html = client.post("/login", content=big, headers={"Content-Type": "text/plain"})
    assert html.headers["content-type"].startswith("text/html")


def test_a_streamed_large_body_is_refused_too(client: TestClient) -> None:
    def chunks() -> Iterator[bytes]:
        for _ in range(100):
            yield b" " * 1024

    r = client.post(f"{API}/users", content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413


def test_a_body_within_the_limit_is_read_whole(client: TestClient) -> None:
    padded = json.dumps({"login": "nobody", "password": "x"}) + " " * (60 * 1024)
    r = client.post(f"{API}/session", content=padded, headers={"Content-Type": "application/json"})
    assert r.status_code == 401


_SERVER = """
import sys, uvicorn
from server.app import create_app
from server.kit.db import upgrade
from server.kit.settings import Settings
settings = Settings(dev_mode=True, data_dir=sys.argv[1], cookie_secure=False)
upgrade(settings.resolved_database_url)
app = create_app(settings, background=False)
uvicorn.run(app, fd=int(sys.argv[2]), log_level="warning")
"""


@pytest.fixture
def live_server(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], int]]:
    """A real uvicorn server in its own process, on a socket bound here (no port race)."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    port = listener.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-c", _SERVER, str(tmp_path), str(listener.fileno())],
        pass_fds=[listener.fileno()],
        cwd=ROOT,
    )
    listener.close()
    try:
        deadline = time.monotonic() + 180
        while True:
            assert proc.poll() is None, "the server exited"
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                assert time.monotonic() < deadline, "the server did not start"
                time.sleep(0.2)
        yield proc, port
    finally:
        proc.terminate()
        proc.wait(timeout=60)


def _rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


def _stream_100_mib(port: int, path: str, content_type: str) -> tuple[int, bytes]:
    """POST 100 MiB in chunks, stopping as soon as an answer arrives; (bytes sent, answer)."""
    chunk = b"x" * (256 * 1024)
    framed = f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
    sent = 0
    answer = b""
    with socket.create_connection(("127.0.0.1", port), timeout=120) as conn:
        conn.sendall(
            f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {content_type}\r\n"
            "Transfer-Encoding: chunked\r\n\r\n".encode()
        )
        try:
            while sent < 100 * 1024 * 1024:
                if select.select([conn], [], [], 0)[0]:
                    break  # the server answered
                conn.sendall(framed)
                sent += len(chunk)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed: its answer is waiting to be read
        try:
            while b"\r\n" not in answer and (got := conn.recv(65536)):
                answer += got
        except ConnectionResetError:
            pass
    return sent, answer


def test_a_100_mib_body_is_refused_early_and_the_server_memory_does_not_grow(
    live_server: tuple[subprocess.Popen[bytes], int],
) -> None:
    proc, port = live_server
    httpx.post(f"http://127.0.0.1:{port}{API}/session", json={"login": "x", "password": "y"})
    before = _rss(proc.pid)
    for path, ctype in [
        (f"{API}/users", "application/json"),
        ("/login", "application/x-www-form-urlencoded"),
        (f"{API}/tokens", "application/json"),
    ]:
        sent, answer = _stream_100_mib(port, path, ctype)
        assert answer.startswith(b"HTTP/1.1 413"), (path, answer[:80])
        assert sent < 50 * 1024 * 1024, (path, sent)  # answered long before the end
    grown = _rss(proc.pid) - before
    print(f"server RSS grew by {grown / 2**20:.1f} MiB over three 100 MiB bodies")
    assert grown < 32 * 1024 * 1024


# --- next= ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("next_path", "location"),
    [
        ("/\u2215/evil", "/%E2%88%95/evil"),
        ("/challenges/caf\u00e9?x=\u00ff#top", "/challenges/caf%C3%A9?x=%C3%BF#top"),
        ("//evil.example", "/account"),
        ("https://evil.example/", "/account"),
        ("/\t/evil.example", "/account"),
    ],
)
def test_login_goes_on_to_a_local_next_path_whatever_its_characters(
    client: TestClient, db: Session, next_path: str, location: str
) -> None:
    make_user(db, "nina")
    visitor = browser(client)
    token = csrf_of(visitor.get("/login").text)
    r = visitor.post(
        "/login",
        data={"csrf_token": token, "login": "nina", "password": PASSWORD, "next": next_path},
    )
    assert r.status_code == 303, r.text
    assert r.headers["location"] == location
    assert "manieval_session" in r.cookies


# --- Login throttling -------------------------------------------------------------------------


def _from(client: TestClient, address: str) -> TestClient:
    return TestClient(client.app, base_url="http://testserver", client=(address, 40000))


def _login(c: TestClient, login: str, password: str) -> httpx.Response:
    return c.post(f"{API}/session", json={"login": login, "password": password})


ATTACKER, OWNER_HOME, ATTACKER_2 = "203.0.113.7", "198.51.100.9", "203.0.113.8"


def test_username_and_email_share_one_bucket_per_account_and_address(
    client: TestClient, db: Session
) -> None:
    make_user(db, "olga")
    attacker = _from(client, ATTACKER)
    codes = [_login(attacker, login, "wrong" * 3).status_code for login in ["olga"] * 3]
    codes += [_login(attacker, "OLGA@example.org", "wrong" * 3).status_code for _ in range(2)]
    assert codes == [401] * 5  # the default: 5 failures per hour per (account, address)
    sixth = _login(attacker, "olga@example.org", "wrong" * 3)
    assert sixth.status_code == 429
    assert int(sixth.headers["Retry-After"]) > 0
    assert _login(attacker, "olga", "wrong" * 3).status_code == 429


def test_the_owner_still_logs_in_from_a_fresh_address_while_an_attacker_hammers(
    client: TestClient, db: Session
) -> None:
    make_user(db, "oscar")
    attacker, owner = _from(client, ATTACKER), _from(client, OWNER_HOME)
    for _ in range(20):
        _login(attacker, "oscar", "guess" * 3)
    assert _login(attacker, "oscar", "guess" * 3).status_code == 429
    # The attacker's address is throttled for this account, even with the right password...
    assert _login(attacker, "oscar", PASSWORD).status_code == 429
    # ...but the owner, elsewhere, is not: nobody can lock an account out.
    assert _login(owner, "oscar", PASSWORD).status_code == 200
    assert _login(owner, "oscar@example.org", PASSWORD).status_code == 200
    # A second attacking address gets its own allowance, not the owner's.
    assert _login(_from(client, ATTACKER_2), "oscar", "guess" * 3).status_code == 401


def test_successes_are_not_counted(client: TestClient, db: Session) -> None:
    make_user(db, "pia")
    home = _from(client, OWNER_HOME)
    assert all(_login(home, "pia", PASSWORD).status_code == 200 for _ in range(12))


def test_an_unknown_name_is_throttled_like_an_account(client: TestClient) -> None:
    attacker = _from(client, ATTACKER)
    codes = [_login(attacker, "nobody-here", "wrong" * 3).status_code for _ in range(6)]
    assert codes == [401] * 5 + [429]  # the same answers as for a real account: no oracle


def test_an_address_is_throttled_across_accounts(
    client: TestClient, db: Session, settings: Settings
) -> None:
    app: Any = client.app
    app.state.services.settings = settings.model_copy(
        update={"login_failures_per_address": "4/hour"}
    )
    for name in ("quinn", "rosa"):
        make_user(db, name)
    attacker = _from(client, ATTACKER)
    codes = [_login(attacker, name, "wrong" * 3).status_code for name in ("quinn", "rosa") * 2]
    assert codes == [401] * 4
    assert _login(attacker, "quinn", PASSWORD).status_code == 429
    assert _login(_from(client, OWNER_HOME), "quinn", PASSWORD).status_code == 200


def test_the_login_form_is_throttled_the_same_way(client: TestClient, db: Session) -> None:
    make_user(db, "sven")
    attacker = TestClient(client.app, base_url="http://testserver", client=(ATTACKER, 1))
    token = csrf_of(attacker.get("/login").text)
    form = {"csrf_token": token, "login": "sven", "password": "wrong" * 3}
    pages = [attacker.post("/login", data=form) for _ in range(6)]
    assert [p.status_code for p in pages] == [200] * 6  # the form again (docs/web.md)
    assert all("Wrong username, email or password." in p.text for p in pages[:5])
    assert "too many failed logins" in pages[5].text
    assert "too many failed logins" in attacker.post("/login", data=form).text


# --- Passwords ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("password", "reason"),
    [
        ("passwordpassword", "Repeats like"),
        ("abcdefghij", "Sequences like"),
        ("p@ssw0rd123", "similar to a commonly used password"),
        ("Passw0rd12", "similar to a commonly used password"),
    ],
)
def test_weak_passwords_are_refused_with_zxcvbns_reason(
    client: TestClient, password: str, reason: str
) -> None:
    body = {"username": "tara", "email": "tara@example.org", "password": password}
    r = client.post(f"{API}/users", json=body)
    assert r.status_code == 422
    problem = r.json()["error"]["fields"]["password"]
    assert "too easy to guess" in problem
    assert reason in problem
    visitor = browser(client)
    token = csrf_of(visitor.get("/register").text)
    page = visitor.post("/register", data={**body, "csrf_token": token})
    assert page.status_code == 200  # the form again, with the reason
    assert "too easy to guess" in page.text
    assert reason.replace('"', "&#34;") in page.text or reason in page.text


def test_the_minimum_score_is_a_setting(client: TestClient, settings: Settings) -> None:
    app: Any = client.app
    app.state.services.settings = settings.model_copy(update={"password_min_score": 1})
    body = {"username": "ugo", "email": "ugo@example.org", "password": "Passw0rd12"}
    assert client.post(f"{API}/users", json=body).status_code == 201


# --- Settings and helpers -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "field", ["login_failures_per_address", "login_failures_per_account_address"]
)
def test_a_bad_throttling_rate_is_refused_at_startup(tmp_path: Path, field: str) -> None:
    with pytest.raises(ValueError, match="invalid rate"):
        Settings(dev_mode=True, data_dir=tmp_path, **{field: "lots"})

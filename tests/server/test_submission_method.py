"""A submission's method: its name and links to its paper and code, in the API, the submit form
and the CLI; links other than absolute http(s) URLs never reach a page."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from manieval.client import MethodInfo
from server.kit.errors import Invalid
from server.submissions.method import Method, link_problem
from testkit.factories import make_challenge, make_user, token_for

API = "/api/v1"
IMAGE = "127.0.0.1:5000/team/policy:v1"
PAPER = "https://arxiv.org/abs/2302.04659"
CODE = "http://example.org:8080/lab/policy?rev=2#readme"
REFUSED = [
    "javascript:alert(1)",
    "data:text/html,<script>alert(1)</script>",
    "ftp://example.org/paper.pdf",
    "https://",
    "//example.org/paper",
    "example.org/paper",
    "https://example.org/a paper",
    "https://example.org:port/",
    "https://example.org/\u0000",
    "https://example.org/" + "a" * 500,
    "HTTPS://example.org/paper",  # the API's pattern is lower case: so is the form's check
]


@pytest.mark.parametrize("url", ["", PAPER, CODE, "https://[::1]:8443/x"])
def test_absolute_http_links_are_kept(url: str) -> None:
    assert link_problem(url) is None


@pytest.mark.parametrize("url", REFUSED)
def test_other_links_are_refused_with_a_reason(url: str) -> None:
    assert link_problem(url)


def test_an_edit_clears_with_empty_text_and_leaves_what_it_does_not_name() -> None:
    assert Method(name=" ", paper_url="").checked().stored() == {"method": None, "paper_url": None}
    assert Method(name=" ACT ").checked().stored() == {"method": "ACT"}
    with pytest.raises(Invalid) as refused:
        Method(name="x" * 101, paper_url="javascript:1", code_url=PAPER).checked()
    assert set(refused.value.fields) == {"method", "paper_url"}
    with pytest.raises(Invalid) as reordering:
        Method(name="ACT\u202e1.0 erocs").checked()  # would show the rest of a cell reversed
    assert set(reordering.value.fields) == {"method"}


@pytest.fixture
def alice(client: TestClient, db: Session) -> dict[str, str]:
    make_challenge(db)
    make_user(db, "alice")
    return token_for(client, "alice")


def test_the_api_keeps_shows_and_edits_the_method(
    client: TestClient, alice: dict[str, str]
) -> None:
    body = {"challenge": "server-tiny", "image": IMAGE, "method": "ACT", "paper_url": PAPER}
    made = client.post(f"{API}/submissions", json=body, headers=alice)
    assert made.status_code == 202, made.text
    sid = made.json()["id"]
    shown = client.get(f"{API}/submissions/{sid}", headers=alice).json()
    assert (shown["method"], shown["paper_url"], shown["code_url"]) == ("ACT", PAPER, None)

    patch = {"paper_url": "", "code_url": CODE}
    edited = client.patch(f"{API}/submissions/{sid}", json=patch, headers=alice)
    assert edited.status_code == 200, edited.text
    assert (edited.json()["method"], edited.json()["paper_url"]) == ("ACT", None)
    assert edited.json()["code_url"] == CODE


@pytest.mark.parametrize("url", ["javascript:alert(1)", "https://", "ftp://example.org/x"])
def test_the_api_refuses_a_link_that_is_no_web_address(
    client: TestClient, alice: dict[str, str], url: str
) -> None:
    body = {"challenge": "server-tiny", "image": IMAGE, "code_url": url}
    refused = client.post(f"{API}/submissions", json=body, headers=alice)
    assert refused.status_code == 422, refused.text
    assert "code_url" in refused.text
    assert client.get(f"{API}/submissions", headers=alice).json()["total"] == 0


def test_the_document_states_the_link_grammar(client: TestClient) -> None:
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    for name in ("SubmitIn", "SubmissionPatch"):
        paper = schemas[name]["properties"]["paper_url"]
        variants = paper.get("anyOf", [paper])
        assert any(v.get("pattern", "").startswith("^$|^https?://") for v in variants), paper
        method = schemas[name]["properties"]["method"]
        patterns = [v.get("pattern", "") for v in method.get("anyOf", [method])]
        assert any("\\u202e" in p for p in patterns), method  # direction controls refused


def test_the_cli_refuses_a_link_before_anything_is_uploaded() -> None:
    assert MethodInfo("ACT", PAPER, CODE).link_problem() is None
    assert MethodInfo(code_url="javascript:alert(1)").link_problem() == (
        "--code-url",
        "'javascript:alert(1)' is not an absolute http:// or https:// URL",
    )
    assert MethodInfo(method="ACT").fields() == {"method": "ACT"}

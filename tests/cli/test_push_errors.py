"""How `manieval push` words an engine's failure: each kind its message and exit code."""

from __future__ import annotations

import pytest
import typer

from manieval.engine_login import Engine
from manieval.push import Target, _push_refused, split_reference, target_for

ENGINE = Engine("podman", "/usr/bin/podman")
TARGET = Target(domain="127.0.0.1:5000", repository="alice/policy", tag="v1")
BLOB = "Copying blob sha256:4291ad429413401c0ffee4134290000000000000000000000000000000000000"


@pytest.mark.parametrize(
    ("line", "code", "words"),
    [
        (
            "Error: pinging container registry 127.0.0.1:5000: dial tcp: connection refused",
            24,
            "does not answer",
        ),
        (
            "Error: ... unable to retrieve auth token: invalid username/password: unauthorized",
            23,
            "run manieval login again",
        ),
        (
            "Error: writing blob: denied: requested access to the resource is denied",
            23,
            "you may push only under 127.0.0.1:5000/alice/",
        ),
        ("Error: writing blob: StatusCode: 413, Request Entity Too Large", 23, "too large"),
        ("Error: toomanyrequests: storage quota of alice reached", 23, "(quota)"),
        ("Error: something else entirely", 23, "podman push failed"),
    ],
)
def test_each_refusal_has_its_message_and_code(
    line: str, code: int, words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(typer.Exit) as exited:
        _push_refused(ENGINE, TARGET, [BLOB, line])
    assert exited.value.exit_code == code
    assert words in capsys.readouterr().err


def test_digits_inside_a_digest_are_not_an_http_status(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(typer.Exit):
        _push_refused(ENGINE, TARGET, [BLOB, "Error: something else entirely"])
    assert "quota" not in capsys.readouterr().err


def test_the_target_keeps_the_local_name_and_tag_under_the_users_namespace() -> None:
    assert target_for(
        "localhost/team/p:v2", domain="r:5000", namespace="bob", name=None, tag=None
    ) == (Target(domain="r:5000", repository="bob/p", tag="v2"))
    assert target_for("my-policy", domain="r:5000", namespace="bob", name=None, tag=None).tag == (
        "latest"
    )
    assert target_for("x:1", domain="r", namespace="bob", name="Walker", tag="t").tagged == (
        "r/bob/walker:t"
    )
    assert split_reference("127.0.0.1:5000/a/b") == ("127.0.0.1:5000/a/b", None)


def test_a_bad_repository_name_is_refused_before_anything_is_pushed() -> None:
    with pytest.raises(ValueError, match="not a repository name"):
        target_for("x", domain="r", namespace="bob", name="-bad", tag=None)

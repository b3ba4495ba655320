import hashlib
import re

import argon2
import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.kit import security

# --- Passwords -----------------------------------------------------------------------------------


def test_hash_password_verifies_the_same_password():
    assert security.verify_password(security.hash_password("tidy-gripper-42"), "tidy-gripper-42")


def test_verify_password_refuses_a_different_password():
    password_hash = security.hash_password("tidy-gripper-42")
    assert not security.verify_password(password_hash, "tidy-gripper-43")
    assert not security.verify_password(password_hash, "")


def test_hash_password_uses_argon2id_with_the_owasp_parameters():
    parameters = argon2.extract_parameters(security.hash_password("tidy-gripper-42"))
    assert parameters.type is argon2.Type.ID
    assert (parameters.memory_cost, parameters.time_cost, parameters.parallelism) == (19456, 2, 1)


def test_hash_password_salts_every_hash():
    assert security.hash_password("tidy-gripper-42") != security.hash_password("tidy-gripper-42")


@pytest.mark.parametrize(
    "bad_hash",
    [
        "",
        "garbage",
        "$argon2id$garbage",
        "$argon2id$v=19$m=19456,t=2,p=1$c2FsdHNhbHRzYWx0$",
        "$2b$12$R9h/cIPz0gi.URNNX3kh2OPST9/PgBkqquzi.Ss7KIUgO2t0jWMUW",
        "é" * 40,
    ],
)
def test_verify_password_is_false_for_a_malformed_hash(bad_hash: str):
    assert security.verify_password(bad_hash, "tidy-gripper-42") is False


def test_verify_password_is_false_for_a_truncated_hash():
    password_hash = security.hash_password("tidy-gripper-42")
    assert security.verify_password(password_hash[:-4], "tidy-gripper-42") is False


def test_password_needs_rehash_is_false_for_a_fresh_hash():
    assert not security.password_needs_rehash(security.hash_password("tidy-gripper-42"))


def test_password_needs_rehash_flags_a_hash_made_with_other_parameters():
    old = argon2.PasswordHasher(time_cost=1, memory_cost=8192, parallelism=1).hash("x")
    assert security.verify_password(old, "x")
    assert security.password_needs_rehash(old)


def test_password_needs_rehash_flags_a_malformed_hash():
    assert security.password_needs_rehash("garbage")


def test_passwords_are_compared_after_unicode_normalisation():
    # U+FB01 is the "fi" ligature; NFKC turns it into the two letters f and i.
    password_hash = security.hash_password("\ufb01ve-robot-arms")
    assert security.verify_password(password_hash, "five-robot-arms")


def test_a_password_with_a_lone_surrogate_hashes_and_verifies():
    password_hash = security.hash_password("gripper-\ud800-arm")
    assert security.verify_password(password_hash, "gripper-\ud800-arm")
    assert not security.verify_password(password_hash, "gripper--arm")


def test_dummy_verify_does_the_work_of_a_real_verify(monkeypatch: pytest.MonkeyPatch) -> None:
    """Same cost by construction (tests never time things): a real argon2id verify against a
    hash made with exactly the parameters real accounts use."""
    real_params = argon2.extract_parameters(security.hash_password("tidy-gripper-42"))
    calls: list[str] = []
    original = security.verify_password

    def spy(password_hash: str, password: str) -> bool:
        calls.append(password_hash)
        return original(password_hash, password)

    monkeypatch.setattr(security, "verify_password", spy)
    security.dummy_verify("wrong-password")
    assert len(calls) == 1
    assert argon2.extract_parameters(calls[0]) == real_params


# --- Password strength ---------------------------------------------------------------------------


def problems(password: str, *, username: str | None = "ada", email: str | None = None) -> list[str]:
    return security.password_problems(password, username=username, email=email)


def test_a_long_uncommon_password_has_no_problems():
    assert problems("velvet-torque-harbour") == []


def test_a_password_of_exactly_10_characters_is_long_enough():
    assert problems("vt9#kq2!zp") == []


def test_a_password_shorter_than_10_characters_is_refused():
    assert problems("vt9#kq2!z") == ["Use at least 10 characters."]


def test_a_password_of_256_characters_is_allowed_and_257_is_not():
    assert problems("vt9#kq2!zp" * 25 + "abcdef") == []
    assert problems("vt9#kq2!zp" * 25 + "abcdefg") == ["Use at most 256 characters."]


def test_one_character_repeated_is_refused():
    assert problems("zzzzzzzzzzzz") == ["Use more than one character, not the same one repeated."]


def test_a_password_containing_the_username_is_refused_whatever_the_case():
    assert problems("my-AdaLovelace-pw", username="adalovelace") == [
        "Do not include your username in your password."
    ]


def test_a_username_shorter_than_3_characters_is_not_checked():
    assert problems("velvet-torque-harbour", username="ve") == []


def test_a_password_containing_the_email_local_part_is_refused():
    found = problems("velvet-Grace.Hopper", email="grace.hopper@example.org")
    assert found == ["Do not include your email address in your password."]


def test_an_email_local_part_shorter_than_3_characters_is_not_checked():
    assert problems("velvet-torque-harbour", email="ve@example.org") == []


def test_username_and_email_may_be_unknown():
    assert problems("velvet-torque-harbour", username=None, email=None) == []


@pytest.mark.parametrize("password", ["qwertyuiop", "1234567890", "Password123", "QWERTY12345"])
def test_a_very_common_password_is_refused(password: str):
    assert any("most common passwords" in p for p in problems(password))


@pytest.mark.parametrize(
    "password", ["password2024!", "Monkey1234567", "sunshine!!!!", "dragon 2025"]
)
def test_a_common_password_with_digits_or_symbols_appended_is_refused(password: str):
    assert any("most common passwords" in p for p in problems(password))


def test_a_common_word_inside_a_longer_password_is_fine():
    assert problems("dragon-velvet-harbour") == []


def test_every_problem_is_a_sentence():
    found = problems("ada", username="ada", email="ada@example.org")
    assert len(found) >= 2
    for problem in found:
        assert problem[0].isupper()
        assert problem.endswith(".")


def test_the_common_password_list_is_casefolded():
    assert all(p == p.casefold() for p in security.COMMON_PASSWORDS)
    assert len(security.COMMON_PASSWORDS) > 300


# --- Usernames -----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["ada", "robot-lab_2", "0day", "a" * 32, "a__b", "a--b"])
def test_a_valid_username_has_no_problem(name: str):
    assert security.validate_username(name) is None


@pytest.mark.parametrize("name", ["", "ab", "a" * 33])
def test_a_username_must_be_3_to_32_characters(name: str):
    assert security.validate_username(name) == "A username must be 3 to 32 characters long."


@pytest.mark.parametrize(
    "name",
    [
        "-ada",
        "_ada",
        "ada lovelace",
        "ada\n",
        "ádá",
        "\uff41\uff44\uff41",
        "ada@x",
        # Not a registry namespace (the OCI grammar): the user could push nothing.
        "ada_",
        "ada-",
        "x_-",
        "a_-b",
        "a___b",
        "a.b",
    ],
)
def test_a_username_is_ascii_letters_digits_dash_and_underscore(name: str):
    problem = security.validate_username(name)
    assert problem is not None
    assert problem.startswith("A username may contain only")


@pytest.mark.parametrize("name", ["Ada", "ADA", "dora_K-2"])
def test_a_username_may_hold_capitals_as_its_owner_writes_it(name: str):
    assert security.validate_username(name) is None


@pytest.mark.parametrize(
    "name", ["admin", "root", "api", "system", "manieval", "manieval-puller", "Admin", "ROOT"]
)
def test_a_reserved_username_is_refused(name: str):
    assert security.validate_username(name) == "This username is reserved; choose another."


# --- Opaque secrets ------------------------------------------------------------------------------


def test_a_new_api_token_has_the_documented_format():
    issued = security.new_secret("token")
    assert re.fullmatch(r"mev_[a-z2-7]{8}_[A-Za-z0-9_-]{43}", issued.plaintext)
    assert issued.plaintext[4:12] == issued.prefix
    assert issued.digest == hashlib.sha256(issued.plaintext.encode()).hexdigest()


def test_a_new_session_id_has_the_session_tag():
    assert re.fullmatch(
        r"mes_[a-z2-7]{8}_[A-Za-z0-9_-]{43}", security.new_secret("session").plaintext
    )


def test_new_secrets_are_unique():
    issued = [security.new_secret("token") for _ in range(200)]
    assert len({s.plaintext for s in issued}) == 200
    assert len({s.prefix for s in issued}) == 200


def test_an_issued_secret_does_not_show_its_plaintext_in_its_repr():
    issued = security.new_secret("token")
    assert issued.plaintext not in repr(issued)
    assert issued.prefix in repr(issued)


@pytest.mark.parametrize("kind", ["token", "session"])
def test_parse_secret_returns_the_prefix_and_digest_of_an_issued_secret(kind: security.SecretKind):
    issued = security.new_secret(kind)
    assert security.parse_secret(issued.plaintext, kind) == (issued.prefix, issued.digest)


def test_parse_secret_refuses_a_secret_of_the_other_kind():
    assert security.parse_secret(security.new_secret("session").plaintext, "token") is None
    assert security.parse_secret(security.new_secret("token").plaintext, "session") is None


VALID = "mev_abcdefgh_" + "A" * 42 + "Q"


def test_the_valid_example_parses():
    assert security.parse_secret(VALID, "token") is not None


@pytest.mark.parametrize(
    "text",
    [
        "",
        VALID[:-1],
        VALID + "A",
        " " + VALID[:-1],
        VALID.replace("mev_", "mex_"),
        VALID.replace("mev_", "MEV_"),
        VALID.replace("abcdefgh", "ABCDEFGH"),
        VALID.replace("abcdefgh", "abcdefg1"),
        VALID.replace("abcdefgh", "abcdefg_"),
        VALID.replace("mev_abcdefgh_", "mev-abcdefgh-"),
        VALID[:-1] + "=",
        VALID[:-1] + "+",
        VALID[:-1] + "/",
        VALID[:-1] + "é",
        VALID[:-1] + "B",  # a non-zero spare bit: not a base64 encoding we would issue
    ],
)
def test_parse_secret_refuses_malformed_text(text: str):
    assert security.parse_secret(text, "token") is None


@given(st.text())
def test_parse_secret_never_raises(text: str):
    assert security.parse_secret(text, "token") is None or text.startswith("mev_")


def test_secrets_equal_compares_digests():
    digest = security.new_secret("token").digest
    assert security.secrets_equal(digest, digest)
    assert not security.secrets_equal(digest, digest[:-1] + ("0" if digest[-1] != "0" else "1"))
    assert not security.secrets_equal(digest, digest[:-1])
    assert not security.secrets_equal(digest, "é")


# --- CSRF ----------------------------------------------------------------------------------------

KEY = b"k" * 32


def test_a_csrf_token_is_valid_for_its_session():
    digest = security.new_secret("session").digest
    assert security.csrf_valid(security.csrf_token(digest, KEY), digest, KEY)


def test_a_csrf_token_is_stable_for_a_session():
    digest = security.new_secret("session").digest
    assert security.csrf_token(digest, KEY) == security.csrf_token(digest, KEY)


def test_a_csrf_token_is_invalid_for_another_session():
    token = security.csrf_token(security.new_secret("session").digest, KEY)
    assert not security.csrf_valid(token, security.new_secret("session").digest, KEY)


def test_a_csrf_token_is_invalid_under_another_key():
    digest = security.new_secret("session").digest
    assert not security.csrf_valid(security.csrf_token(digest, KEY), digest, b"j" * 32)


@pytest.mark.parametrize("token", [None, "", "x", "é" * 43])
def test_a_missing_or_malformed_csrf_token_is_invalid(token: str | None):
    assert not security.csrf_valid(token, security.new_secret("session").digest, KEY)


def test_a_tampered_csrf_token_is_invalid():
    digest = security.new_secret("session").digest
    token = security.csrf_token(digest, KEY)
    tampered = token[:-1] + ("A" if token[-1] != "A" else "B")
    assert not security.csrf_valid(tampered, digest, KEY)


def test_a_csrf_key_shorter_than_32_bytes_is_refused():
    with pytest.raises(ValueError, match="at least 32 bytes"):
        security.csrf_token("digest", b"short")

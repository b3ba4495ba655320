"""Passwords, opaque secrets (API tokens, sessions) and CSRF tokens: pure functions, no I/O."""

from __future__ import annotations

import base64
import binascii
import functools
import hashlib
import hmac
import re
import secrets
import string
import unicodedata
from dataclasses import dataclass, field
from typing import Literal

from argon2 import PasswordHasher, Type
from argon2.exceptions import InvalidHashError, VerificationError
from zxcvbn import zxcvbn

# --- Passwords -----------------------------------------------------------------------------------

# OWASP Password Storage Cheat Sheet, "Argon2id": "a minimum configuration of 19 MiB of memory, an
# iteration count of 2, and 1 degree of parallelism" (m=19456 KiB, t=2, p=1).
# https://cheatsheetseries.owasp.org/cheatsheets/Password_Storage_Cheat_Sheet.html#argon2id
# Changing these later is safe: `password_needs_rehash` flags old hashes at the next login.
_HASHER = PasswordHasher(
    time_cost=2, memory_cost=19 * 1024, parallelism=1, hash_len=32, salt_len=16, type=Type.ID
)

MIN_PASSWORD_LENGTH = 10
MAX_PASSWORD_LENGTH = 256
DEFAULT_MIN_SCORE = 3
"""zxcvbn's "safely unguessable: moderate protection from offline slow-hash scenario"."""
ZXCVBN_MAX_LENGTH = 72


def _password_bytes(password: str) -> bytes:
    # NIST SP 800-63B 5.1.1.2 asks for Unicode normalisation (NFKC) before hashing, so the same
    # password typed on two keyboards gives the same bytes. `surrogatepass` keeps a lone surrogate
    # (possible in JSON input) from raising: such a password is simply hashed as those bytes.
    return unicodedata.normalize("NFKC", password).encode("utf-8", "surrogatepass")


def hash_password(password: str) -> str:
    """Hash a password with argon2id (a fresh random salt each call)."""
    return str(_HASHER.hash(_password_bytes(password)))


def verify_password(password_hash: str, password: str) -> bool:
    """Whether `password` matches `password_hash`; False (never an exception) for a bad hash."""
    if not password_hash.isascii():
        return False
    try:
        return bool(_HASHER.verify(password_hash, _password_bytes(password)))
    except (VerificationError, InvalidHashError):
        return False


def password_needs_rehash(password_hash: str) -> bool:
    """Whether a hash that just verified was made with other parameters than today's."""
    try:
        return bool(_HASHER.check_needs_rehash(password_hash))
    except InvalidHashError:
        return True


@functools.cache
def _dummy_hash() -> str:
    return hash_password(secrets.token_urlsafe(16))


def dummy_verify(password: str) -> None:
    """Spend what a real `verify_password` costs, for logins naming an unknown account."""
    # Built on first use, so the first call in a process costs one extra hash; only that one.
    verify_password(_dummy_hash(), password)


def password_problems(
    password: str,
    *,
    username: str | None,
    email: str | None,
    min_score: int = DEFAULT_MIN_SCORE,
) -> list[str]:
    """Why `password` is too weak for this account, one sentence per problem; empty when fine."""
    normalized = unicodedata.normalize("NFKC", password)
    folded = normalized.casefold()
    problems = []
    if len(normalized) < MIN_PASSWORD_LENGTH:
        problems.append(f"Use at least {MIN_PASSWORD_LENGTH} characters.")
    if len(normalized) > MAX_PASSWORD_LENGTH:
        problems.append(f"Use at most {MAX_PASSWORD_LENGTH} characters.")
    if len(set(normalized)) == 1:
        problems.append("Use more than one character, not the same one repeated.")
    if username and len(username) >= 3 and username.casefold() in folded:
        problems.append("Do not include your username in your password.")
    local_part = email.rpartition("@")[0] if email and "@" in email else ""
    if len(local_part) >= 3 and local_part.casefold() in folded:
        problems.append("Do not include your email address in your password.")
    if _is_common(folded):
        problems.append(
            "This is one of the most common passwords (or one with digits or symbols added), "
            "which attackers try first; choose a less predictable one."
        )
    if not problems and len(normalized) <= MAX_PASSWORD_LENGTH:
        problems.extend(_strength_problems(normalized, [username or "", local_part], min_score))
    return problems


def _strength_problems(password: str, user_inputs: list[str], min_score: int) -> list[str]:
    # zxcvbn estimates the guesses an attacker needs (dictionaries, keyboard patterns, dates,
    # l33t substitutions, repeats, sequences) and says why in words: that reason is shown.
    # zxcvbn's cost grows quickly with length, so it refuses more than 72 characters: the first
    # 72 are judged, and a password is never weaker than a prefix of it.
    estimate = zxcvbn(
        password[:ZXCVBN_MAX_LENGTH], user_inputs=[text for text in user_inputs if text]
    )
    if estimate["score"] >= min_score:
        return []
    feedback = estimate["feedback"]
    reasons = [str(feedback.get("warning") or "")] + [str(s) for s in feedback["suggestions"]]
    return [
        f"This password is too easy to guess (strength {estimate['score']} of 4, "
        f"at least {min_score} needed).",
        *(reason for reason in reasons if reason),
    ]


_TRAILING_NOISE = string.digits + string.punctuation + string.whitespace


def _is_common(folded: str) -> bool:
    # With a 10-character minimum most common passwords are refused by length already; what gets
    # through is a common word with digits or symbols appended ("password2024!"), so strip those.
    base = folded.rstrip(_TRAILING_NOISE)
    return folded in COMMON_PASSWORDS or (len(base) >= 4 and base in COMMON_PASSWORDS)


# The ~250 most common passwords of SecLists' 10-million-password-list-top-10000.txt (MIT licence,
# github.com/danielmiessler/SecLists, Passwords/Common-Credentials) in its order, then ~130
# entries of that file that are at least 10 characters long, then a few names of this service;
# all casefolded. Kept in the module so no data file has to be packaged.
COMMON_PASSWORDS = frozenset(
    """
123456 password 12345678 qwerty 123456789 12345 1234 111111 1234567 dragon 123123 baseball abc123
football monkey letmein 696969 shadow master 666666 qwertyuiop 123321 mustang 1234567890 michael
654321 pussy superman 1qaz2wsx 7777777 fuckyou 121212 000000 qazwsx 123qwe killer trustno1 jordan
jennifer zxcvbnm asdfgh hunter buster soccer harley batman andrew tigger sunshine iloveyou fuckme
2000 charlie robert thomas hockey ranger daniel starwars klaster 112233 george asshole computer
michelle jessica pepper 1111 zxcvbn 555555 11111111 131313 freedom 777777 pass fuck maggie 159753
aaaaaa ginger princess joshua cheese amanda summer love ashley 6969 nicole chelsea biteme matthew
access yankees 987654321 dallas austin thunder taylor matrix william corvette hello martin heather
secret fucker merlin diamond 1234qwer gfhjkm hammer silver 222222 88888888 anthony justin test
bailey q1w2e3r4t5 patrick internet scooter orange 11111 golfer cookie richard samantha bigdog
guitar jackson whatever mickey chicken sparky snoopy maverick phoenix camaro sexy peanut morgan
welcome falcon cowboy ferrari samsung andrea smokey steelers joseph mercedes dakota arsenal eagles
melissa boomer booboo spider nascar monster tigers yellow xxxxxx 123123123 gateway marina diablo
bulldog qwer1234 compaq purple hardcore banana junior hannah 123654 porsche lakers iceman money
cowboys 987654 london tennis 999999 ncc1701 coffee scooby 0000 miller boston q1w2e3r4 fuckoff
brandon yamaha chester mother forever johnny edward 333333 oliver redsox player nikita knight
fender barney midnight please brandy chicago badboy iwantu slayer rangers charles angel flower
bigdaddy rabbit wizard bigdick jasper enter rachel chris steven winner adidas victoria natasha
1q2w3e4r jasmine winter prince panties marine ghbdtn fishing cocacola casper james
1q2w3e4r5t 4815162342 1234554321 123456789a 1029384756 password123 123qweasdzxc 0987654321
12345qwert 1111111111 123456789q 12345678910 1qaz2wsx3edc 0123456789 1123581321 q1w2e3r4t5y6
1q2w3e4r5t6y qwerty12345 1234512345 usuckballz1 soso123aljg basketball christopher manchester
mailcreated5240 1122334455 qazwsxedcrfv fuck_inside 123456qwerty 1234567890q 0000000000
5555555555 terminator 9876543210 nuttertools rjirfrgbde california enterprise sojdlg123aljg
poiuytrewq translator fktrcfylhf deepthroat multiplelo undertaker qwerty123456 motherlode
sersolution montgom240 qwerty1234 salamander tinkerbell qwertyqwerty 123456654321 motherfucker
realmadrid polniypizdec0211 1357924680 7ugd5hip2j leavemealone dragonball 1234567890a
gfhjkmgfhjkm 1234567891 vsjasnel12 qazwsxedc123 9293709b13 yjdsqgfhjkm good123654 7894561230
harrypotter zxcvbnm123 strawberry washington abrakadabra 7777777777 alessandro ghjcnjgfhjkm
zxcasdqwe123 qwert12345 underground 123456789s highlander 0192837465 konstantin intercourse
9999999999 12345qwerty sonyericsson penetration skateboard mississippi ironmaiden hellokitty
university htubcnhfwbz suckmydick masterbate vqsablpzla roadrunner nthvbyfnjh tokiohotel
anastasiya evangelion absolutely password12 ghhh47hj7649 playstation aleksandra aaaaaaaaaa
1234509876 123456789qwe 1234567899 2222222222 1qazxsw23edc 1212121212 123456789m 123456789d
qwerasdfzxcv azertyuiop liverpool1 masterbating vfntvfnbrf cheerleaers ghjcnbnenrf experienced
dragonballz password99 revolution cocksucker 1234567890-
admin manieval maniskill
""".split()
)

# --- Usernames -----------------------------------------------------------------------------------

# A registry repository's path component (the OCI distribution grammar, without '.'), since a
# username is its owner's namespace in the service's registry: separators only between letters
# and digits.
# A user name keeps the case its owner typed, for display; it is matched and unique regardless
# of case (server/accounts/service.py, migration 0009). A team name is lowercase only: its page
# is /teams/{name}.
USERNAME_GRAMMAR = r"[A-Za-z0-9]+(?:(?:_|__|-+)[A-Za-z0-9]+)*"
TEAM_NAME_GRAMMAR = r"[a-z0-9]+(?:(?:_|__|-+)[a-z0-9]+)*"
_USERNAME = re.compile(USERNAME_GRAMMAR)

# Names that would let an account pass for the service, its staff, or a URL of the site.
RESERVED_USERNAMES = frozenset(
    """
admin administrator root superuser sudo system sysadmin api www web mail email postmaster
hostmaster webmaster abuse security support help info contact staff team moderator mod official
manieval manieval-puller maniskill null none undefined anonymous guest nobody everyone me self
user users account
accounts login logout signin signup register settings profile dashboard static assets docs status
health challenges submissions leaderboard leaderboards new edit delete
""".split()
)


def validate_username(name: str) -> str | None:
    """Why `name` cannot be a username, or None when it can."""
    if not 3 <= len(name) <= 32:
        return "A username must be 3 to 32 characters long."
    if not _USERNAME.fullmatch(name):
        return (
            "A username may contain only letters a-z and A-Z, digits, '-' and '_', "
            "must start and end with a letter or a digit, and may not have '_' next to '-'."
        )
    if name.lower() in RESERVED_USERNAMES:
        return "This username is reserved; choose another."
    return None


# --- Opaque secrets: API tokens and sessions -----------------------------------------------------

SecretKind = Literal["token", "session"]

# A recognisable leading tag lets secret scanners (GitHub's, gitleaks) spot a leaked token.
_TAGS: dict[SecretKind, str] = {"token": "mev", "session": "mes"}
_PREFIX_BYTES = 5  # 40 random bits, exactly 8 base32 characters
_SECRET_BYTES = 32  # 256 random bits, 43 urlsafe-base64 characters
_SECRET_PATTERNS = {
    kind: re.compile(rf"{tag}_([a-z2-7]{{8}})_([A-Za-z0-9_-]{{43}})") for kind, tag in _TAGS.items()
}
_SECRET_LENGTH = 3 + 1 + 8 + 1 + 43


@dataclass(frozen=True)
class IssuedSecret:
    """A new secret: show `plaintext` once, store `prefix` and `digest`."""

    plaintext: str = field(repr=False)
    prefix: str
    digest: str


def new_secret(kind: SecretKind) -> IssuedSecret:
    """A fresh API token (`mev_<prefix>_<secret>`) or session id (`mes_...`)."""
    prefix = base64.b32encode(secrets.token_bytes(_PREFIX_BYTES)).decode("ascii").lower()
    secret = base64.urlsafe_b64encode(secrets.token_bytes(_SECRET_BYTES)).decode("ascii")
    plaintext = f"{_TAGS[kind]}_{prefix}_{secret.rstrip('=')}"
    return IssuedSecret(plaintext=plaintext, prefix=prefix, digest=_digest(plaintext))


def parse_secret(text: str, kind: SecretKind) -> tuple[str, str] | None:
    """`(prefix, digest)` of a presented secret of this kind, or None when it is malformed.

    Find the stored row by its prefix (or its digest) and compare digests with `secrets_equal`.
    """
    if len(text) != _SECRET_LENGTH:
        return None
    match = _SECRET_PATTERNS[kind].fullmatch(text)
    if match is None or not _is_canonical_base64(match[2]):
        return None
    return match[1], _digest(text)


def _is_canonical_base64(text: str) -> bool:
    # 43 characters carry 258 bits; a secret we issued has the 2 spare bits zero.
    try:
        raw = base64.urlsafe_b64decode(text + "=")
    except binascii.Error:
        return False
    return base64.urlsafe_b64encode(raw).decode("ascii").rstrip("=") == text


def _digest(plaintext: str) -> str:
    # A plain SHA-256, not argon2: with 256 random bits there is nothing to brute-force, so a slow
    # hash would only add latency to every authenticated request. It also makes the digest a
    # deterministic lookup key. (Passwords are low-entropy, which is why they get argon2id.)
    return hashlib.sha256(plaintext.encode("ascii")).hexdigest()


def secrets_equal(a_digest: str, b_digest: str) -> bool:
    """Compare two digests in time that does not depend on where they differ."""
    return hmac.compare_digest(
        a_digest.encode("utf-8", "surrogatepass"), b_digest.encode("utf-8", "surrogatepass")
    )


# --- CSRF ----------------------------------------------------------------------------------------

# OWASP CSRF Prevention Cheat Sheet, "signed double-submit cookie": an HMAC of the session, so a
# token is useless with any other session and needs no server-side storage.
_CSRF_CONTEXT = b"manieval-csrf-v1:"
MIN_CSRF_KEY_BYTES = 32


def csrf_token(session_digest: str, key: bytes) -> str:
    """The CSRF token for a session: HMAC-SHA256 of its digest under `key`, urlsafe base64."""
    if len(key) < MIN_CSRF_KEY_BYTES:
        raise ValueError(f"the CSRF key must be at least {MIN_CSRF_KEY_BYTES} bytes long")
    mac = hmac.new(
        key, _CSRF_CONTEXT + session_digest.encode("utf-8", "surrogatepass"), hashlib.sha256
    )
    return base64.urlsafe_b64encode(mac.digest()).decode("ascii").rstrip("=")


def csrf_valid(token: str | None, session_digest: str, key: bytes) -> bool:
    """Whether `token` is this session's CSRF token (constant-time); False when missing."""
    expected = csrf_token(session_digest, key)
    if token is None:
        return False
    return hmac.compare_digest(token.encode("utf-8", "surrogatepass"), expected.encode("ascii"))

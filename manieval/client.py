"""An HTTP client of the ManiEval API (``/api/v1``), as the participant commands use it.

Every failure is a `ClientError`: `Unreachable` when no answer came back, `ApiError` when the
server answered with an error (its ``{"error": {"code", "message", "fields"}}`` body read into
attributes), `NotLoggedIn` when a call needs a token and there is none.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any
from urllib.parse import quote, urlsplit

from manieval import __version__

if TYPE_CHECKING:  # httpx is imported when a client is made: `manieval --help` needs none
    import httpx

DEFAULT_SERVER = "http://127.0.0.1:8000"
API = "/api/v1"
CONNECT_S = 10.0
READ_S = 30.0
IDLE_S = 2.0
"""How long an idle connection is kept for the next call: less than the server's keep-alive
(uvicorn closes after 5 s), so that no call is sent on a connection the server is closing (the
call would fail with "connection reset by peer", a race a slow poll meets)."""
IDEMPOTENT = frozenset({"GET", "HEAD", "PUT", "DELETE"})
"""Methods whose call is sent once more when the connection breaks before an answer (RFC 9110,
9.2.2): a reused connection the server was closing, on a machine too busy to keep the margin
`IDLE_S` leaves."""
# Submitting resolves the image through its registry (several requests, each with its own
# server-side timeout): give it longer than a plain read.
SUBMIT_READ_S = 120.0
DOWNLOAD_READ_S = 120.0  # a trajectory file: up to MANIEVAL_MAX_TRAJECTORY_BYTES
EPISODES_PAGE = 1000  # the most the episodes endpoint gives per page

JSON = dict[str, Any]


class ClientError(Exception):
    """Anything that kept a call from getting its answer."""


class Unreachable(ClientError):
    def __init__(self, server: str, reason: str) -> None:
        super().__init__(f"cannot reach {server}: {reason}")
        self.server = server
        self.reason = reason


class NotLoggedIn(ClientError):
    def __init__(self, server: str, *, other: str | None = None) -> None:
        super().__init__(f"not logged in to {server}")
        self.server = server
        self.other = other  # the server the saved login is for, if another one


@dataclass
class ApiError(ClientError):
    """The server's error answer."""

    status: int
    code: str
    message: str
    fields: dict[str, str] = field(default_factory=dict)
    retry_after: float | None = None
    resets_at: datetime | None = None
    authenticated: bool = False  # whether the request carried an API token
    server: str = ""

    def __post_init__(self) -> None:
        super().__init__(self.message)

    @classmethod
    def from_response(
        cls, response: httpx.Response, *, server: str, authenticated: bool
    ) -> ApiError:
        body: Any = None
        try:
            body = response.json()
        except ValueError:
            pass
        error = body.get("error") if isinstance(body, dict) else None
        if not isinstance(error, dict) or not isinstance(error.get("code"), str):
            # Not our error shape: a proxy, or not a ManiEval server at all.
            return cls(
                status=response.status_code,
                code="http_error",
                message=f"HTTP {response.status_code} {response.reason_phrase} from "
                f"{response.request.url}",
                retry_after=_retry_after(response, None),
                authenticated=authenticated,
                server=server,
            )
        fields = error.get("fields")
        return cls(
            status=response.status_code,
            code=error["code"],
            message=str(error.get("message", "")),
            fields={str(k): str(v) for k, v in fields.items()} if isinstance(fields, dict) else {},
            retry_after=_retry_after(response, error.get("retry_after")),
            resets_at=_datetime(error.get("resets_at")),
            authenticated=authenticated,
            server=server,
        )


def _retry_after(response: httpx.Response, in_body: object) -> float | None:
    header = response.headers.get("Retry-After")
    if header is not None and header.strip().isdigit():
        return float(header)
    return float(in_body) if isinstance(in_body, int | float) else None


def _datetime(value: object) -> datetime | None:
    if not isinstance(value, str):
        return None
    try:
        return datetime.fromisoformat(value)
    except ValueError:
        return None


def normalise_server(url: str) -> str:
    """`http(s)://host[:port][/prefix]` without the trailing slash, or ValueError."""
    url = url.strip().rstrip("/")
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{url!r} is not a server URL: give http(s)://HOST[:PORT]")
    return url


def is_loopback(server: str) -> bool:
    """Whether the server URL names this machine: ``localhost`` or a loopback address
    (127.0.0.0/8, ::1). A name that merely begins with ``127.`` is another machine: plain HTTP
    to it is warned about (a password) or refused (registry credentials) like any other.

    The server's side of the rule is `server.registry.own.loopback_domain` (the server does not
    import this package) and the SDK's is `manieval_sdk.openpi.mapping.loopback_url`."""
    host = urlsplit(server).hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def is_loopback_domain(domain: str) -> bool:
    """`is_loopback` for a registry's ``HOST[:PORT]`` (``[::1]:5000`` for IPv6)."""
    return is_loopback(f"//{domain}")


@dataclass(frozen=True)
class MethodInfo:
    """What a submission may say of its method (`--method`, `--paper-url`, `--code-url`)."""

    method: str | None = None
    paper_url: str | None = None
    code_url: str | None = None

    def fields(self) -> dict[str, str]:
        """The body fields given (the server checks the links)."""
        given = {"method": self.method, "paper_url": self.paper_url, "code_url": self.code_url}
        return {k: v for k, v in given.items() if v is not None}

    def link_problem(self) -> tuple[str, str] | None:
        """(option, why) for a link the server will refuse, or None; the server checks all."""
        for option, url in (("--paper-url", self.paper_url), ("--code-url", self.code_url)):
            if url and (urlsplit(url).scheme not in ("http", "https") or not urlsplit(url).netloc):
                return option, f"{url!r} is not an absolute http:// or https:// URL"
        return None


class Client:
    """One server, with or without an API token. Use it as a context manager."""

    def __init__(
        self, server: str, *, token: str | None = None, transport: httpx.BaseTransport | None = None
    ) -> None:
        self.server = server
        self.token = token
        import httpx

        headers = {"User-Agent": f"manieval-cli/{__version__}"}
        if token is not None:
            headers["Authorization"] = f"Bearer {token}"
        self._http = httpx.Client(
            base_url=server,
            headers=headers,
            timeout=httpx.Timeout(READ_S, connect=CONNECT_S),
            limits=httpx.Limits(keepalive_expiry=IDLE_S),
            transport=transport,
        )

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self._http.close()

    def request(
        self,
        method: str,
        path: str,
        *,
        json: JSON | None = None,
        params: dict[str, str | int] | None = None,
        read_s: float = READ_S,
    ) -> httpx.Response:
        """One API call; raises `Unreachable` or `ApiError` unless the answer is a 2xx."""
        import httpx

        timeout = httpx.Timeout(read_s, connect=CONNECT_S)
        tries = 2 if method.upper() in IDEMPOTENT else 1
        try:
            for tried in range(1, tries + 1):
                try:
                    response = self._http.request(
                        method, API + path, json=json, params=params, timeout=timeout
                    )
                    break
                except (httpx.ReadError, httpx.WriteError, httpx.RemoteProtocolError):
                    if tried == tries:  # the broken connection is dropped: the next is new
                        raise
        except httpx.TimeoutException:
            raise Unreachable(self.server, f"no answer within {read_s:.0f} s") from None
        except httpx.TransportError as exc:
            reason = re.sub(r"^\[Errno -?\d+\] ", "", str(exc)) or type(exc).__name__
            raise Unreachable(self.server, reason) from None
        if response.is_error:
            raise ApiError.from_response(
                response, server=self.server, authenticated=self.token is not None
            )
        return response

    def call(self, method: str, path: str, **kwargs: Any) -> Any:
        """`request`, then the JSON body (an `ApiError` if it is not JSON)."""
        response = self.request(method, path, **kwargs)
        try:
            return response.json()
        except ValueError:
            raise ApiError(
                status=response.status_code,
                code="not_json",
                message=f"{self.server} did not answer with JSON",
                server=self.server,
            ) from None

    # Accounts ---------------------------------------------------------------------------------

    def register(self, *, username: str, email: str, password: str) -> JSON:
        body = {"username": username, "email": email, "password": password}
        result: JSON = self.call("POST", "/users", json=body)
        return result

    def create_token(self, *, login: str, password: str, name: str) -> JSON:
        """A new API token by password (its value is in this answer only)."""
        body = {"login": login, "password": password, "name": name}
        result: JSON = self.call("POST", "/auth/token", json=body)
        return result

    def revoke_token(self, token_id: int) -> JSON:
        result: JSON = self.call("DELETE", f"/tokens/{token_id}")
        return result

    def me(self) -> JSON:
        result: JSON = self.call("GET", "/me")
        return result

    # Challenges and leaderboards --------------------------------------------------------------

    def challenges(self) -> list[JSON]:
        """Every challenge, all pages."""
        items: list[JSON] = []
        page = 1
        while True:
            found = self.call("GET", "/challenges", params={"page": page, "per_page": 200})
            items += found["items"]
            if not found["items"] or len(items) >= found["total"]:
                return items
            page += 1

    def challenge(self, slug: str) -> JSON:
        result: JSON = self.call("GET", f"/challenges/{_segment(slug)}")
        return result

    def leaderboard(
        self, slug: str, *, phase: str, page: int, per_page: int, format: str = "json"
    ) -> httpx.Response:
        """The raw answer: JSON or CSV bytes exactly as the server rendered them."""
        params: dict[str, str | int] = {
            "phase": phase,
            "page": page,
            "per_page": per_page,
            "format": format,
        }
        return self.request("GET", f"/challenges/{_segment(slug)}/leaderboard", params=params)

    # Submissions ------------------------------------------------------------------------------

    def submit(
        self,
        *,
        challenge: str,
        phase: str,
        image: str,
        description: str,
        public: bool,
        method: MethodInfo | None = None,
        track: str | None = None,
    ) -> JSON:
        body: dict[str, object] = {
            "challenge": challenge,
            "phase": phase,
            "image": image,
            "description": description,
            "public": public,
        }
        if track is not None:  # a server from before tracks refuses the field
            body["track"] = track
        body.update((method or MethodInfo()).fields())
        result: JSON = self.call("POST", "/submissions", json=body, read_s=SUBMIT_READ_S)
        return result

    def submission(self, submission_id: int) -> JSON:
        result: JSON = self.call("GET", f"/submissions/{submission_id}")
        return result

    def my_submissions(self, *, challenge: str | None, per_page: int) -> list[JSON]:
        """My newest submissions first."""
        params: dict[str, str | int] = {"per_page": per_page}
        if challenge is not None:
            params["challenge"] = challenge
        items: list[JSON] = self.call("GET", "/submissions", params=params)["items"]
        return items

    def episodes(self, submission_id: int) -> list[JSON]:
        """Every episode record of the current attempt, all pages (owner and admins only)."""
        items: list[JSON] = []
        page = 1
        while True:
            params: dict[str, str | int] = {"page": page, "per_page": EPISODES_PAGE}
            found = self.call("GET", f"/submissions/{submission_id}/episodes", params=params)
            items += found["items"]
            if not found["items"] or len(items) >= found["total"]:
                return items
            page += 1

    def logs(self, submission_id: int) -> JSON:
        result: JSON = self.call("GET", f"/submissions/{submission_id}/logs")
        return result

    def trajectories(self, submission_id: int) -> JSON:
        """The current attempt's trajectory files, one `.h5` + `.json` pair per task run."""
        result: JSON = self.call("GET", f"/submissions/{submission_id}/trajectories")
        return result

    def download(self, url: str, target: Path) -> int:
        """Write the file at `url` (a path the API gave, under /api/v1) to `target`, whole or
        not at all; its size in bytes."""
        if not url.startswith(API + "/"):
            raise ValueError(f"{url!r} is not a path of the API")
        data = self.request("GET", url.removeprefix(API), read_s=DOWNLOAD_READ_S).content
        partial = target.with_name(target.name + ".part")
        partial.write_bytes(data)
        partial.replace(target)
        return len(data)

    def cancel(self, submission_id: int) -> JSON:
        result: JSON = self.call("POST", f"/submissions/{submission_id}/cancel")
        return result

    def mark_final(self, submission_id: int, *, final: bool = True) -> JSON:
        """Make it my final choice in its phase (or, `final` False, take the mark off)."""
        method = "PUT" if final else "DELETE"
        result: JSON = self.call(method, f"/submissions/{submission_id}/final")
        return result

    def post_deadline(self, slug: str, *, phase: str) -> JSON:
        """The phase's post-deadline board: what was submitted after it closed."""
        path = f"/challenges/{_segment(slug)}/post-deadline"
        result: JSON = self.call("GET", path, params={"phase": phase})
        return result

    # Teams ------------------------------------------------------------------------------------

    def my_team(self) -> JSON:
        """My team (None when I am in none) and the invitations waiting for my answer."""
        result: JSON = self.call("GET", "/team")
        return result

    def team(self, name: str) -> JSON:
        result: JSON = self.call("GET", f"/teams/{_segment(name)}")
        return result

    def create_team(self, *, name: str, display_name: str) -> JSON:
        body = {"name": name, "display_name": display_name}
        result: JSON = self.call("POST", "/teams", json=body)
        return result

    def invite(self, *, team: str, username: str) -> JSON:
        body = {"username": username}
        result: JSON = self.call("POST", f"/teams/{_segment(team)}/invitations", json=body)
        return result

    def revoke_invitation(self, *, team: str, invitation_id: int) -> JSON:
        result: JSON = self.call("DELETE", f"/teams/{_segment(team)}/invitations/{invitation_id}")
        return result

    def accept_invitation(self, invitation_id: int) -> JSON:
        result: JSON = self.call("POST", f"/team/invitations/{invitation_id}/accept")
        return result

    def decline_invitation(self, invitation_id: int) -> JSON:
        result: JSON = self.call("POST", f"/team/invitations/{invitation_id}/decline")
        return result

    def leave_team(self) -> JSON:
        result: JSON = self.call("POST", "/team/leave")
        return result

    def remove_member(self, *, team: str, username: str) -> JSON:
        path = f"/teams/{_segment(team)}/members/{_segment(username)}"
        result: JSON = self.call("DELETE", path)
        return result


def speaks_api(server: str) -> bool:
    """Whether `server` answers the API's public challenge list (False: a wrong URL or path)."""
    try:
        with Client(server) as client:
            found = client.call("GET", "/challenges", params={"per_page": 1})
    except ApiError:
        return False
    except ClientError:
        return True  # no answer says nothing about the path
    return isinstance(found, dict) and isinstance(found.get("items"), list)


def _segment(value: str) -> str:
    """A user-given path segment, quoted so that it stays one segment."""
    return quote(value, safe="")

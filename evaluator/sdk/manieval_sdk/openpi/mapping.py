"""The mapping file: which ManiSkill observation entries become which keys of an openpi server's
request, how images are resized, and how the server's actions come back.

A TOML file (docs/policy-servers.md describes every field)::

    [server]
    url = "ws://127.0.0.1:8000"
    command = "python3 /opt/policy/serve_policy.py --port 8000"

    [[image]]
    key = "observation/image"
    source = "sensor_data/base_camera/rgb"
    size = [224, 224]

    [[state]]
    key = "observation/state"
    sources = ["agent/qpos", "extra/tcp_pose"]

    [prompt]
    key = "prompt"

    [actions]
    dims = 7
    horizon = 5

Pure: reading and checking the file needs only the standard library.
"""

from __future__ import annotations

import ipaddress
import shlex
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

DEFAULT_URL = "ws://127.0.0.1:8000"
DEFAULT_STARTUP_TIMEOUT_S = 100.0
RESIZE_METHODS = ("bilinear", "nearest")
FITS = ("pad", "stretch")
LAYOUTS = ("hwc", "chw")
STATE_DTYPES = ("float32", "float64")
MAX_IMAGE_SIDE = 4096

Key = tuple[str, ...]
"""Where a value goes in the request: ("observation/image",) for openpi's flat keys, or
("images", "cam_high") for a nested request."""

ObsPath = tuple[str, ...]
"""Where a value comes from in ManiSkill's observation: ("sensor_data", "base_camera", "rgb")."""


class MappingError(ValueError):
    """The mapping file is missing, unreadable or wrong; the message says where and why."""


@dataclass(frozen=True)
class ServerConfig:
    url: str
    command: tuple[str, ...] | None
    startup_timeout_s: float


@dataclass(frozen=True)
class ImageInput:
    key: Key
    source: ObsPath
    size: tuple[int, int] | str | None
    """[height, width]; a str names the metadata entry that holds it; None: as observed."""
    resize: str
    fit: str
    layout: str


@dataclass(frozen=True)
class StateInput:
    key: Key
    sources: tuple[ObsPath, ...]
    dtype: str


@dataclass(frozen=True)
class PromptInput:
    key: Key
    default: str | None


@dataclass(frozen=True)
class ActionOutput:
    key: str
    dims: int | None
    """Keep the first `dims` values of each action (a server may pad); None: all of them."""
    horizon: int | None
    """Execute at most this many actions of a chunk before asking again; None: all of them."""


@dataclass(frozen=True)
class Mapping:
    server: ServerConfig
    images: tuple[ImageInput, ...]
    states: tuple[StateInput, ...]
    prompt: PromptInput | None
    actions: ActionOutput


def loopback_url(url: str) -> str:
    """`url` if it is a ws:// address on this machine's loopback; MappingError otherwise."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme != "ws" or port is None:
        raise MappingError(f"the server URL must be ws://HOST:PORT, not {url!r}")
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise MappingError(
                f"the server URL {url!r} is not on the loopback interface: the policy server "
                "runs in the same container (127.0.0.1, ::1 or localhost)"
            )
    return url


def load_mapping(path: str | Path) -> Mapping:
    """Read and check a mapping file."""
    path = Path(path)
    try:
        document = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise MappingError(f"{path}: cannot read the mapping file: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise MappingError(f"{path}: not valid TOML: {exc}") from None
    try:
        return parse_mapping(document)
    except MappingError as exc:
        raise MappingError(f"{path}: {exc}") from None


def parse_mapping(document: dict[str, Any]) -> Mapping:
    """Check a mapping read from TOML; MappingError names the table and field at fault."""
    _known(document, "the mapping", {"server", "image", "state", "prompt", "actions"})
    images = tuple(
        _image(table, f"[[image]] #{n}")
        for n, table in enumerate(_tables(document, "image"), start=1)
    )
    states = tuple(
        _state(table, f"[[state]] #{n}")
        for n, table in enumerate(_tables(document, "state"), start=1)
    )
    prompt = None
    if "prompt" in document:
        prompt = _prompt(_table(document, "prompt"))
    if not images and not states and prompt is None:
        raise MappingError("it maps nothing: give at least one [[image]], [[state]] or [prompt]")
    keys = [i.key for i in images] + [s.key for s in states] + ([prompt.key] if prompt else [])
    for key in keys:
        clashes = [other for other in keys if other != key and other[: len(key)] == key]
        if keys.count(key) > 1 or clashes:
            raise MappingError(f"the request key {_show(key)} is given more than once")
    return Mapping(
        server=_server(_table(document, "server") if "server" in document else {}),
        images=images,
        states=states,
        prompt=prompt,
        actions=_actions(_table(document, "actions") if "actions" in document else {}),
    )


def _server(table: dict[str, Any]) -> ServerConfig:
    where = "[server]"
    _known(table, where, {"url", "command", "startup_timeout_s"})
    url = loopback_url(_str(table, "url", where, default=DEFAULT_URL))
    command: tuple[str, ...] | None = None
    if "command" in table:
        raw = table["command"]
        if isinstance(raw, str):
            command = tuple(shlex.split(raw))
        elif isinstance(raw, list) and all(isinstance(part, str) for part in raw):
            command = tuple(raw)
        else:
            raise MappingError(f"{where} command must be a string or a list of strings")
        if not command:
            raise MappingError(f"{where} command is empty")
    timeout = table.get("startup_timeout_s", DEFAULT_STARTUP_TIMEOUT_S)
    if isinstance(timeout, bool) or not isinstance(timeout, int | float) or not timeout > 0:
        raise MappingError(f"{where} startup_timeout_s must be a positive number of seconds")
    return ServerConfig(url=url, command=command, startup_timeout_s=float(timeout))


def _image(table: dict[str, Any], where: str) -> ImageInput:
    _known(table, where, {"key", "source", "size", "resize", "fit", "layout"})
    size: tuple[int, int] | str | None = None
    if "size" in table:
        raw = table["size"]
        if isinstance(raw, str) and raw:
            size = raw
        else:
            size = image_size(raw, f"{where} size")
    return ImageInput(
        key=_key(table, where),
        source=_path(table.get("source"), f"{where} source"),
        size=size,
        resize=_choice(table, "resize", RESIZE_METHODS, where),
        fit=_choice(table, "fit", FITS, where),
        layout=_choice(table, "layout", LAYOUTS, where),
    )


def image_size(raw: Any, where: str) -> tuple[int, int]:
    """A [height, width] pair of sensible pixel counts, or MappingError saying what it got."""
    if (
        isinstance(raw, list | tuple)
        and len(raw) == 2
        and all(type(n) is int and 1 <= n <= MAX_IMAGE_SIDE for n in raw)
    ):
        return int(raw[0]), int(raw[1])
    raise MappingError(
        f"{where} must be [height, width] in pixels (1 to {MAX_IMAGE_SIDE}) or the name of a "
        f"metadata entry that holds them, not {raw!r}"
    )


def _state(table: dict[str, Any], where: str) -> StateInput:
    _known(table, where, {"key", "sources", "dtype"})
    sources = table.get("sources")
    if not isinstance(sources, list) or not sources:
        raise MappingError(f"{where} sources must be a non-empty list of observation paths")
    return StateInput(
        key=_key(table, where),
        sources=tuple(_path(s, f"{where} sources") for s in sources),
        dtype=_choice(table, "dtype", STATE_DTYPES, where),
    )


def _prompt(table: dict[str, Any]) -> PromptInput:
    where = "[prompt]"
    _known(table, where, {"key", "default"})
    default = table.get("default")
    if default is not None and not isinstance(default, str):
        raise MappingError(f"{where} default must be a string")
    return PromptInput(key=_key({"key": "prompt", **table}, where), default=default)


def _actions(table: dict[str, Any]) -> ActionOutput:
    where = "[actions]"
    _known(table, where, {"key", "dims", "horizon"})
    counts: dict[str, int | None] = {}
    for name in ("dims", "horizon"):
        value = table.get(name)
        if value is not None and (type(value) is not int or value < 1):
            raise MappingError(f"{where} {name} must be a positive integer, not {value!r}")
        counts[name] = value
    return ActionOutput(
        key=_str(table, "key", where, default="actions"),
        dims=counts["dims"],
        horizon=counts["horizon"],
    )


def _tables(document: dict[str, Any], name: str) -> list[dict[str, Any]]:
    tables = document.get(name, [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise MappingError(f"{name} must be an array of tables: write [[{name}]] above each")
    return tables


def _table(document: dict[str, Any], name: str) -> dict[str, Any]:
    table = document[name]
    if not isinstance(table, dict):
        raise MappingError(f"{name} must be a table: write [{name}] above its fields")
    return table


def _known(table: dict[str, Any], where: str, fields: set[str]) -> None:
    unknown = sorted(set(table) - fields)
    if unknown:
        raise MappingError(
            f"{where} has unknown field(s) {', '.join(unknown)} "
            f"(known: {', '.join(sorted(fields))})"
        )


def _str(table: dict[str, Any], name: str, where: str, *, default: str) -> str:
    value = table.get(name, default)
    if not isinstance(value, str) or not value:
        raise MappingError(f"{where} {name} must be a non-empty string")
    return value


def _choice(table: dict[str, Any], name: str, choices: tuple[str, ...], where: str) -> str:
    value = table.get(name, choices[0])
    if value not in choices:
        raise MappingError(f"{where} {name} must be one of {', '.join(choices)}, not {value!r}")
    return str(value)


def _key(table: dict[str, Any], where: str) -> Key:
    raw = table.get("key")
    if isinstance(raw, str) and raw:
        return (raw,)
    if isinstance(raw, list) and raw and all(isinstance(p, str) and p for p in raw):
        return tuple(raw)
    raise MappingError(
        f"{where} key must be the server's key (a string), or a list of strings for a nested one"
    )


def _path(raw: Any, where: str) -> ObsPath:
    if isinstance(raw, str):
        parts = tuple(raw.split("/"))
        if all(parts):
            return parts
    raise MappingError(
        f"{where}: an observation path is a string such as 'sensor_data/base_camera/rgb', "
        f"not {raw!r}"
    )


def _show(key: Key) -> str:
    return repr(key[0]) if len(key) == 1 else repr(list(key))

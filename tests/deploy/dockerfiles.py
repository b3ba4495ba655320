"""Dockerfiles and .dockerignore as data: just enough of their grammar for the checks here."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from tests.deploy.manifests import REPO

DOCKER = REPO / "docker"
DOCKERFILES = sorted(DOCKER.glob("*/Dockerfile"))
_VARIABLE = re.compile(r"\$\{?(\w+)\}?")


@dataclass(frozen=True)
class Instruction:
    keyword: str
    args: str


@dataclass
class Stage:
    name: str | None
    base: str
    """The FROM reference with the global ARG defaults substituted."""
    instructions: list[Instruction] = field(default_factory=list)


def instructions(path: Path) -> list[Instruction]:
    """The instructions of a Dockerfile, continuation lines joined, comments dropped."""
    found, pending = [], ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if pending and line.startswith("#"):
            continue  # a comment inside a continued instruction
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        text = pending + line
        pending = ""
        keyword, _, args = text.partition(" ")
        found.append(Instruction(keyword.upper(), args.strip()))
    return found


def stages(path: Path) -> list[Stage]:
    """The build stages in order, with FROM references resolved from the global ARGs."""
    defaults: dict[str, str] = {}
    result: list[Stage] = []
    for instruction in instructions(path):
        if instruction.keyword == "FROM":
            words = [w for w in instruction.args.split() if not w.startswith("--")]
            reference = _VARIABLE.sub(lambda m: defaults.get(m.group(1), m.group(0)), words[0])
            name = words[2] if len(words) == 3 and words[1].upper() == "AS" else None
            result.append(Stage(name=name, base=reference))
        elif not result and instruction.keyword == "ARG":
            key, _, value = instruction.args.partition("=")
            defaults[key] = value
        elif result:
            result[-1].instructions.append(instruction)
    return result


def copy_from(instruction: Instruction) -> str | None:
    """The stage a COPY takes files from, if any."""
    match = re.search(r"--from=(\S+)", instruction.args)
    return match.group(1) if match else None


def final_stages(all_stages: list[Stage]) -> list[Stage]:
    """Stages no other stage builds on or copies from: the images a build can produce."""
    used = {s.base for s in all_stages}
    used |= {copy_from(i) for s in all_stages for i in s.instructions if i.keyword == "COPY"}
    return [s for s in all_stages if s.name not in used]


def effective_user(stage: Stage, all_stages: list[Stage]) -> str | None:
    """The USER a stage runs as, looking through the stages it builds on."""
    by_name = {s.name: s for s in all_stages if s.name}
    current: Stage | None = stage
    while current is not None:
        users = [i.args for i in current.instructions if i.keyword == "USER"]
        if users:
            return users[-1]
        current = by_name.get(current.base)
    return None


def copy_sources(path: Path) -> list[str]:
    """What the COPY instructions take from the build context (not from other stages)."""
    sources = []
    for stage in stages(path):
        for i in stage.instructions:
            if i.keyword == "COPY" and copy_from(i) is None:
                words = [w for w in i.args.split() if not w.startswith("--")]
                sources += words[:-1]
    return sources


def dockerignore_patterns(
    path: Path = REPO / ".dockerignore",
) -> list[tuple[bool, re.Pattern[str]]]:
    """(exclude?, pattern) in file order, as Docker reads .dockerignore."""
    patterns = []
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        exclude = not line.startswith("!")
        glob = line.lstrip("!").strip("/")
        regex = ""
        i = 0
        while i < len(glob):
            if glob.startswith("**/", i):
                regex += "(?:.*/)?"
                i += 3
            elif glob.startswith("**", i):
                regex += ".*"
                i += 2
            elif glob[i] == "*":
                regex += "[^/]*"
                i += 1
            elif glob[i] == "?":
                regex += "[^/]"
                i += 1
            elif glob[i] == "[":
                end = glob.index("]", i)
                regex += glob[i : end + 1]
                i = end + 1
            else:
                regex += re.escape(glob[i])
                i += 1
        patterns.append((exclude, re.compile(regex)))
    return patterns


def ignored(relative: str, patterns: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether Docker leaves this path out of the build context: the last pattern that matches
    the path or one of its parent directories decides."""
    parts = relative.strip("/").split("/")
    prefixes = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    decision = False
    for exclude, pattern in patterns:
        if any(pattern.fullmatch(prefix) for prefix in prefixes):
            decision = exclude
    return decision

"""What a policy may see of an observation: the suite's `observation_keys`, enforced."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from fnmatch import fnmatchcase
from typing import Any

Path = tuple[str, ...]


def _is_space_leaf(value: Any) -> bool:
    """A leaf of a task spec's `observation_space`: `{"shape": [...], "dtype": "..."}`."""
    return isinstance(value, dict) and {"shape", "dtype"} <= value.keys()


class ObservationKeys:
    """Keeps the entries of a (nested) observation that a path pattern names, with everything
    below them, and drops the rest; no patterns (None) keeps everything."""

    def __init__(self, patterns: Sequence[str] | None) -> None:
        self._patterns = None if patterns is None else [tuple(p.split("/")) for p in patterns]

    def observation(self, obs: Any) -> Any:
        """The observation as the policy sees it."""
        if self._patterns is not None and not isinstance(obs, dict):
            raise ValueError(
                "observation_keys select entries of a dict observation, not a flat one"
            )
        return self._select(obs, (), lambda value: not isinstance(value, dict))

    def space(self, description: dict[str, Any]) -> dict[str, Any]:
        """A task spec's `observation_space` with only the entries the policy will see."""
        kept: dict[str, Any] = self._select(description, (), _is_space_leaf)
        return kept

    def _select(self, node: Any, path: Path, is_leaf: Callable[[Any], bool]) -> Any:
        if self._patterns is None or is_leaf(node):
            return node
        kept = {}
        for key, value in node.items():
            below = (*path, str(key))
            if self._names(below):
                kept[key] = value
            elif not is_leaf(value) and self._leads_into(below):
                inner = self._select(value, below, is_leaf)
                if inner:
                    kept[key] = inner
        return kept

    def _names(self, path: Path) -> bool:
        """Whether a pattern names this entry or one above it."""
        assert self._patterns is not None
        return any(len(p) <= len(path) and _matches(path, p) for p in self._patterns)

    def _leads_into(self, path: Path) -> bool:
        """Whether a pattern names something below this entry."""
        assert self._patterns is not None
        return any(len(p) > len(path) and _matches(path, p) for p in self._patterns)


def _matches(path: Path, pattern: Path) -> bool:
    """Whether the path's first names match the pattern's (as far as both go)."""
    return all(fnmatchcase(name, part) for name, part in zip(path, pattern, strict=False))

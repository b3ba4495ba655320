"""ManiSkill observations into an openpi request, and the server's answer into an action chunk.

Pure functions of numpy arrays: no network, no openpi-client, so they are tested anywhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from manieval_sdk.openpi.mapping import (
    ActionOutput,
    ImageInput,
    Key,
    Mapping,
    MappingError,
    ObsPath,
    image_size,
)

Size = tuple[int, int]


class AnswerError(ValueError):
    """The server's answer is not an action chunk this task can take; the message says why."""


def lookup(obs: Any, path: ObsPath) -> Any:
    """The entry at `path` of a nested observation, or MappingError listing what is there."""
    node = obs
    for depth, name in enumerate(path):
        if not isinstance(node, dict) or name not in node:
            where = "/".join(path[:depth]) or "the observation"
            there = ", ".join(sorted(map(str, node))) if isinstance(node, dict) else ""
            raise MappingError(
                f"{'/'.join(path)}: {where} has no {name!r} (it has: {there or 'nothing'})"
            )
        node = node[name]
    return node


def check_sources(mapping: Mapping, observation_space: dict[str, Any]) -> None:
    """Check, before any episode, that every path the mapping reads is in the task's
    observations and that images are images; MappingError otherwise."""
    if not observation_space:
        return  # an evaluator that does not describe its observations: checked at `act`
    for image in mapping.images:
        leaf = lookup(observation_space, image.source)
        shape = leaf.get("shape") if isinstance(leaf, dict) else None
        if not isinstance(shape, list) or len(shape) not in (2, 3):
            raise MappingError(
                f"[[image]] {'/'.join(image.source)} is not an image (shape {shape}): the "
                "task's obs_mode must give camera data, e.g. rgbd"
            )
    for state in mapping.states:
        for source in state.sources:
            lookup(observation_space, source)


def image_sizes(mapping: Mapping, metadata: Any) -> list[Size | None]:
    """Each image's target size, with names looked up in the server's metadata."""
    sizes: list[Size | None] = []
    for image in mapping.images:
        if isinstance(image.size, str):
            if not isinstance(metadata, dict) or image.size not in metadata:
                have = ", ".join(sorted(map(str, metadata))) if isinstance(metadata, dict) else ""
                raise MappingError(
                    f"[[image]] size names the metadata entry {image.size!r}, which the "
                    f"server's metadata does not have (it has: {have or 'nothing'})"
                )
            value = metadata[image.size]
            value = value.tolist() if isinstance(value, np.ndarray) else value
            sizes.append(image_size(value, f"the server's metadata entry {image.size!r}"))
        else:
            sizes.append(image.size)
    return sizes


def prompt_text(mapping: Mapping, instruction: str | None) -> str | None:
    """What the server gets as its prompt: the task's instruction, else the mapping's default."""
    if mapping.prompt is None:
        return None
    text = instruction or mapping.prompt.default
    if text is None:
        raise MappingError(
            "[prompt]: the task gives no instruction (its suite has none); set [prompt] "
            "default = '...' or remove [prompt]"
        )
    return text


def build_request(
    obs: Any, mapping: Mapping, *, sizes: Sequence[Size | None], prompt: str | None
) -> dict[str, Any]:
    """The request the server gets for this observation."""
    request: dict[str, Any] = {}
    for image, size in zip(mapping.images, sizes, strict=True):
        _put(request, image.key, convert_image(np.asarray(lookup(obs, image.source)), image, size))
    for state in mapping.states:
        parts = [
            np.asarray(lookup(obs, source), dtype=state.dtype).reshape(-1)
            for source in state.sources
        ]
        _put(request, state.key, np.concatenate(parts))
    if mapping.prompt is not None:
        _put(request, mapping.prompt.key, prompt)
    return request


def convert_image(array: np.ndarray, image: ImageInput, size: Size | None) -> np.ndarray:
    """An observed H x W (x C) image resized and laid out as the mapping says."""
    if array.ndim not in (2, 3):
        raise MappingError(f"{'/'.join(image.source)} is not an image (shape {array.shape})")
    if size is not None:
        if image.fit == "pad":
            array = resize_with_pad(array, size, image.resize)
        else:
            array = resize(array, size, image.resize)
    if image.layout == "chw" and array.ndim == 3:
        array = np.ascontiguousarray(np.moveaxis(array, -1, 0))
    return array


def resize(image: np.ndarray, size: Size, method: str = "bilinear") -> np.ndarray:
    """`image` (H x W or H x W x C) resized to `size` (height, width), of the same dtype.

    Pixel centres are aligned (as OpenCV and PIL do); bilinear does not smooth first, so a
    large reduction aliases: prefer sizes within a factor of two of the camera's.
    """
    height, width = image.shape[:2]
    if (height, width) == tuple(size):
        return image
    if method == "nearest":
        rows = _nearest(height, size[0])
        cols = _nearest(width, size[1])
        return np.ascontiguousarray(image[rows][:, cols])
    top, bottom, row_weight = _linear(height, size[0])
    left, right, col_weight = _linear(width, size[1])
    extra = (1,) * (image.ndim - 2)
    row_weight = row_weight.reshape((-1, 1, *extra))
    col_weight = col_weight.reshape((1, -1, *extra))
    pixels = image.astype(np.float64)
    upper = pixels[top][:, left] * (1 - col_weight) + pixels[top][:, right] * col_weight
    lower = pixels[bottom][:, left] * (1 - col_weight) + pixels[bottom][:, right] * col_weight
    blended: np.ndarray = upper * (1 - row_weight) + lower * row_weight
    if image.dtype.kind in "iu":
        limits = np.iinfo(image.dtype)
        blended = np.clip(np.rint(blended), limits.min, limits.max)
    elif image.dtype.kind == "b":
        blended = blended >= 0.5
    return blended.astype(image.dtype)


def resize_with_pad(image: np.ndarray, size: Size, method: str = "bilinear") -> np.ndarray:
    """Resized to fit `size` keeping its aspect ratio, centred and padded with zeros (what
    openpi's clients do with `image_tools.resize_with_pad`)."""
    height, width = image.shape[:2]
    ratio = max(height / size[0], width / size[1])
    inner = (
        min(size[0], max(1, round(height / ratio))),
        min(size[1], max(1, round(width / ratio))),
    )
    resized = resize(image, inner, method)
    if inner == tuple(size):
        return resized
    padded = np.zeros((size[0], size[1], *image.shape[2:]), dtype=image.dtype)
    top = (size[0] - inner[0]) // 2
    left = (size[1] - inner[1]) // 2
    padded[top : top + inner[0], left : left + inner[1]] = resized
    return padded


def _nearest(size_in: int, size_out: int) -> np.ndarray:
    centres = (np.arange(size_out) + 0.5) * (size_in / size_out)
    return np.minimum(centres.astype(np.int64), size_in - 1)


def _linear(size_in: int, size_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    position = np.clip((np.arange(size_out) + 0.5) * (size_in / size_out) - 0.5, 0, size_in - 1)
    low = np.floor(position).astype(np.int64)
    high = np.minimum(low + 1, size_in - 1)
    return low, high, position - low


def _put(request: dict[str, Any], key: Key, value: Any) -> None:
    node = request
    for name in key[:-1]:
        node = node.setdefault(name, {})
    node[key[-1]] = value


def action_chunk(answer: Any, output: ActionOutput, action_shape: tuple[int, ...]) -> np.ndarray:
    """The server's actions as a float32 chunk [H, *action_shape], or AnswerError."""
    if not isinstance(answer, dict) or output.key not in answer:
        have = ", ".join(sorted(map(str, answer))) if isinstance(answer, dict) else type(answer)
        raise AnswerError(f"the server's answer has no {output.key!r} (it has: {have})")
    actions = np.asarray(answer[output.key])
    if actions.dtype.kind not in "fiu":
        raise AnswerError(f"the server's {output.key!r} are not numbers (dtype {actions.dtype})")
    if actions.ndim == 1:
        actions = actions[None]
    if actions.ndim != 2 or actions.shape[0] == 0:
        raise AnswerError(
            f"the server's {output.key!r} must be [H, D] (a chunk of H actions), not shape "
            f"{list(actions.shape)}"
        )
    values = int(np.prod(action_shape))
    if output.dims is not None:
        if output.dims > actions.shape[1]:
            raise AnswerError(
                f"[actions] dims = {output.dims}, but the server's actions have "
                f"{actions.shape[1]} values each"
            )
        actions = actions[:, : output.dims]
    if actions.shape[1] != values:
        hint = f"; set [actions] dims = {values} to keep the first {values}" * (
            actions.shape[1] > values
        )
        raise AnswerError(
            f"the server's actions have {actions.shape[1]} values each, the task takes "
            f"{values}{hint}"
        )
    if output.horizon is not None:
        actions = actions[: output.horizon]
    return actions.astype(np.float32).reshape((actions.shape[0], *action_shape))

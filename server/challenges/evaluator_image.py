"""A challenge's own evaluator image: the project's evaluator with its suite's task packages
added, pinned by digest, which the challenge's Kubernetes Jobs run the evaluator on once the
workers allow it (docs/deploy.md, "Task packages"). Executors that evaluate in the worker's
own environment (the embedded default, the docker executor) run no evaluator image: there
the packages go into that environment, and the image is only kept."""

from __future__ import annotations

from typing import Literal

from evaluator.suite import Suite
from server.kit.errors import Invalid
from server.kit.image_refs import ImageReferenceError, pinned_reference

WORKERS_OWN = "default"
"""`--evaluator-image default`: none of its own; the workers' `MANIEVAL_EVALUATOR_IMAGE`."""


def chosen_evaluator_image(
    *, given: str | None, kept: str | None, kept_versions: dict[str, str], suite: Suite
) -> str | None:
    """The evaluator image a challenge loaded from `suite` names: the one `given` (pinned by
    digest; `WORKERS_OWN`: none), else the one it `kept`, as long as the suite's task packages
    are still those it was loaded with (`kept_versions`): an image built for other versions
    would end every submission `error`, so that reload is refused (Invalid) instead."""
    if given == WORKERS_OWN:
        return None
    if given is not None:
        try:
            return pinned_reference(given)
        except ImageReferenceError as exc:
            raise Invalid(f"evaluator image: {exc}", fields={"evaluator_image": str(exc)}) from None
    if kept is None or kept_versions == suite.package_versions:
        return kept
    raise Invalid(
        f"the challenge's evaluator image {kept} was given for its task packages "
        f"{_versions(kept_versions)}, and the suite now has {_versions(suite.package_versions)}:"
        " name an image with those (--evaluator-image REPO@sha256:<digest>), or"
        f" --evaluator-image {WORKERS_OWN} for the workers' own",
        fields={"evaluator_image": "required: the suite's task packages changed"},
    )


def _versions(versions: dict[str, str]) -> str:
    return ", ".join(f"{name} {version}" for name, version in versions.items()) or "(none)"


def evaluator_image_note(image: str, *, queue: Literal["inline", "celery"]) -> str:
    """What the workers of a service on `queue` make of a challenge's evaluator image."""
    if queue == "inline":
        return (
            f"the embedded worker evaluates in this service's own environment and runs no "
            f"evaluator image: {image} is kept for Kubernetes workers, and the suite's task "
            "packages must be installed here (docs/task-packages.md)"
        )
    return (
        f"Kubernetes workers run this challenge's evaluations on {image} once it is listed in "
        "their MANIEVAL_EVALUATOR_IMAGES (until then its submissions end error, saying so); "
        "workers with the docker executor evaluate in their own environment and ignore it"
    )

"""Run an evaluation, or one shard of it, inside a Kubernetes pod next to the policy's container.

The worker builds the Job (`worker/kubernetes/manifest.py`). Kubernetes starts the policy in its
own container; it connects to the Unix socket this process listens on, in a volume both containers
mount. The outcome goes to stdout between marker lines, where the worker reads it from the
pod's log: the pod holds no credential, and nothing in it can write a result anywhere.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sys
import threading
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Annotated

import typer
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from evaluator.evaluation import build_result
from evaluator.plan import EvaluationPlan, suite_plan, task_run
from evaluator.provenance import installed_versions, local_provenance, merge
from evaluator.results import (
    Abort,
    EpisodeResult,
    EvaluationResult,
    Provenance,
    Versions,
    Video,
)
from evaluator.runner import RunOptions, ShardOutcome, make_shards, run_shard
from evaluator.suite import SEED_LIMIT, Suite, SuiteError

JOB_SPEC_ENV = "MANIEVAL_JOB_SPEC"
JOB_SPEC_FILE_ENV = "MANIEVAL_JOB_SPEC_FILE"
POLICY_ENV = "MANIEVAL_POLICY"
SHARDS_ENV = "MANIEVAL_SHARDS"
ENDPOINT_DIR_ENV = "MANIEVAL_ENDPOINT_DIR"
VIDEO_DIR_ENV = "MANIEVAL_VIDEO_DIR"
TRAJECTORY_DIR_ENV = "MANIEVAL_TRAJECTORY_DIR"
INDEX_ENV = "JOB_COMPLETION_INDEX"  # set by Kubernetes in every pod of an Indexed Job
ENDPOINT_DIR = "/run/manieval/endpoint"
MARK = "MANIEVAL-RESULT"
CHUNK_CHARS = 4000  # well under the 16 KiB at which container runtimes split log lines
SOCKET_UMASK = 0o007  # the policy runs as another user of our group: it must reach the socket


class JobOutputError(ValueError):
    """A pod's log holds no intact result document."""


class EvaluationJob(BaseModel):
    """What one Job evaluates: a suite, a phase and its concrete seeds, never a seed secret."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    suite_yaml: str
    phase: str
    seeds: dict[str, tuple[Annotated[int, Field(ge=0, lt=SEED_LIMIT)], ...]] = Field(min_length=1)
    conditions: tuple[str, ...] | None = None

    def plan(self) -> EvaluationPlan:
        """The plan: the suite's conditions and tasks (in suite order) on these seeds."""
        try:
            suite = Suite.model_validate(yaml.safe_load(self.suite_yaml))
        except (yaml.YAMLError, ValidationError) as exc:
            raise SuiteError(f"invalid suite: {exc}") from None
        suite.phase(self.phase)
        for env_id, seeds in self.seeds.items():
            suite.task(env_id)
            if not seeds:
                raise SuiteError(f"task {env_id!r} has no seeds")
        names = self.conditions or tuple(c.name for c in suite.conditions)
        runs = [
            task_run(suite, task, suite.condition(name), self.seeds[task.env_id])
            for name in names
            for task in suite.tasks
            if task.env_id in self.seeds
        ]
        return suite_plan(
            suite, self.phase, runs, videos=suite.videos, video_conditions=suite.video_conditions
        )

    def canonical_json(self) -> str:
        """The same job always gives the same text (the Job manifest must be deterministic)."""
        return json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))


def evaluation_job(plan: EvaluationPlan, *, suite_yaml: str) -> EvaluationJob:
    """The Job payload that makes a pod rebuild exactly `plan` (ValueError if it cannot)."""
    seeds = {run.env_id: run.seeds for run in plan.runs}
    conditions = tuple(dict.fromkeys(run.condition.name for run in plan.runs))
    job = EvaluationJob(suite_yaml=suite_yaml, phase=plan.phase, seeds=seeds, conditions=conditions)
    recording = {"videos": plan.videos, "video_conditions": plan.video_conditions}
    if job.plan().model_copy(update=recording) != plan:
        raise ValueError("the plan is not the suite's tasks in suite order on one seed list each")
    return job


class ExternalProcess:
    """A policy someone else started (Kubernetes): we cannot see it, only its connection."""

    def alive(self) -> bool:
        """Always: only the connect timeout bounds the wait for it."""
        return True

    def exit_code(self) -> int | None:
        """Unknown here."""
        return None

    def exit_detail(self) -> str | None:
        """Unknown here; the worker reads the policy container's state and log."""
        return None

    def log_tail(self) -> str:
        """Not ours to read: the worker takes it from the policy container's log."""
        return ""

    def stop(self) -> None:
        """Nothing to do: the kubelet stops the policy container when the evaluator exits."""


class ExternalPolicy:
    """A policy source whose process is started by the platform, not by us."""

    def __init__(self, name: str) -> None:
        self.name = name

    def describe(self) -> str:
        """How the result document names the policy (the pinned image)."""
        return self.name

    def pinned_image(self) -> str | None:
        """The policy's image: the Job names it pinned by digest (None: it named none)."""
        return self.name if "@sha256:" in self.name else None

    def launch(self, *, endpoint: str, socket_dir: Path) -> ExternalProcess:
        """Nothing to start: the policy connects to `endpoint` on its own."""
        return ExternalProcess()


class ShardReport(BaseModel):
    """The episodes one pod of an Indexed Job ran, for the worker to merge."""

    model_config = ConfigDict(extra="forbid")

    index: int = Field(ge=0)
    shards: int = Field(ge=1)
    policy: str
    versions: Versions
    provenance: Provenance | None = None
    """Where this shard ran (None from an evaluator image older than schema 1.2)."""
    started_at: datetime
    finished_at: datetime
    episodes: list[tuple[int, EpisodeResult]]
    abort: tuple[int, int, Abort] | None = None
    policy_time_s: float = Field(default=0.0, ge=0)
    videos: list[Video] = []


def run_job(
    plan: EvaluationPlan,
    source: ExternalPolicy,
    *,
    index: int,
    shards: int,
    socket_dir: Path,
    video_dir: Path | None = None,
    trajectory_dir: Path | None = None,
) -> EvaluationResult | ShardReport:
    """Run shard `index` of `shards`; one shard gives the whole result document. Videos (if
    the plan records any) are written to `video_dir`, and every episode's trajectory as a part
    under `trajectory_dir` (`evaluator.trajectory`; the server merges the shards' parts when
    the final report comes): volumes the policy's container lacks."""
    if not 0 <= index < shards:
        raise ValueError(f"shard index {index} is not in 0..{shards - 1}")
    started = datetime.now(UTC)
    # make_shards drops empty shards, and only trailing ones can be empty.
    present = make_shards(plan, shards)
    outcome = ShardOutcome()
    if index < len(present):
        socket_dir.mkdir(parents=True, exist_ok=True)
        previous = os.umask(SOCKET_UMASK)
        try:
            options = RunOptions(
                socket_dir=socket_dir, video_dir=video_dir, trajectory_dir=trajectory_dir
            )
            outcome = run_shard(plan, source, present[index], options=options, on_episode=_progress)
        finally:
            os.umask(previous)
    provenance = local_provenance(plan, policy_image=source.pinned_image())
    if shards == 1:
        return build_result(
            plan, source.describe(), [outcome], started=started, provenance=provenance
        )
    return ShardReport(
        index=index,
        shards=shards,
        policy=source.describe(),
        versions=installed_versions(),
        provenance=provenance,
        started_at=started,
        finished_at=datetime.now(UTC),
        episodes=outcome.episodes,
        abort=outcome.abort,
        policy_time_s=outcome.policy_time_s,
        videos=outcome.videos,
    )


def _progress(run_index: int, episode: EpisodeResult) -> None:
    outcome = episode.failure or ("success" if episode.success_once else "no success")
    print(f"manieval: run {run_index} episode {episode.index}: {outcome}", file=sys.stderr)


def write_document(document: EvaluationResult | ShardReport, out: IO[str]) -> None:
    """Print `document` as marked lines; only lines with the mark belong to it."""
    kind = "result" if isinstance(document, EvaluationResult) else "shard"
    text = json.dumps(document.model_dump(mode="json"), ensure_ascii=True, separators=(",", ":"))
    lines = [f"{MARK} BEGIN {kind}"]
    lines += [f"{MARK} {text[i : i + CHUNK_CHARS]}" for i in range(0, len(text), CHUNK_CHARS)]
    lines.append(f"{MARK} END sha256={hashlib.sha256(text.encode()).hexdigest()}")
    out.write("\n".join(lines) + "\n")
    out.flush()


def read_document(log: str) -> EvaluationResult | ShardReport:
    """The last intact document in a pod's log (other output may be interleaved)."""
    kind: str | None = None
    found: tuple[str, str] | None = None
    chunks: list[str] = []
    for line in log.split("\n"):
        if not line.startswith(MARK + " "):
            continue
        body = line[len(MARK) + 1 :]
        if body.startswith("BEGIN "):
            kind, chunks = body.removeprefix("BEGIN "), []
        elif body.startswith("END sha256=") and kind is not None:
            text = "".join(chunks)
            if hashlib.sha256(text.encode()).hexdigest() == body.removeprefix("END sha256="):
                found = (kind, text)
            kind = None
        elif kind is not None:
            chunks.append(body)
    if found is None:
        raise JobOutputError("the log holds no complete result document")
    try:
        if found[0] == "result":
            return EvaluationResult.model_validate_json(found[1])
        if found[0] == "shard":
            return ShardReport.model_validate_json(found[1])
    except ValidationError as exc:
        raise JobOutputError(f"invalid result document: {exc}") from None
    raise JobOutputError(f"unknown document kind {found[0]!r}")


def result_from_logs(plan: EvaluationPlan, logs: Sequence[str]) -> EvaluationResult:
    """The result document from the evaluator logs of a Job's pods, one per shard index."""
    documents = [read_document(log) for log in logs]
    if len(documents) == 1 and isinstance(documents[0], EvaluationResult):
        return documents[0]
    reports = [d for d in documents if isinstance(d, ShardReport)]
    if len(reports) != len(documents) or [r.index for r in reports] != list(range(len(logs))):
        raise JobOutputError("expected one shard report per index, in index order")
    if any(r.shards != len(logs) for r in reports):
        raise JobOutputError(f"shard reports do not all say {len(logs)} shards")
    outcomes = [
        ShardOutcome(
            episodes=r.episodes, abort=r.abort, policy_time_s=r.policy_time_s, videos=r.videos
        )
        for r in reports
    ]
    return build_result(
        plan,
        reports[0].policy,
        outcomes,
        started=min(r.started_at for r in reports),
        finished=lambda: max(r.finished_at for r in reports),
        versions=reports[0].versions,
        provenance=_merged_provenance(reports),
    )


def _merged_provenance(reports: Sequence[ShardReport]) -> Provenance | None:
    """The shards' provenance merged (`evaluator.provenance.merge`); None when a shard has
    none to give (an older evaluator image)."""
    found = [r.provenance for r in reports if r.provenance is not None]
    return merge(found) if len(found) == len(reports) else None


def load_job(spec: str | None, spec_file: Path | None) -> EvaluationJob:
    """The job from a file, else from JSON text (ValidationError or OSError if bad)."""
    text = spec_file.read_text(encoding="utf-8") if spec_file is not None else spec
    if not text:
        raise ValueError(f"no job spec: set {JOB_SPEC_ENV} or {JOB_SPEC_FILE_ENV}")
    return EvaluationJob.model_validate_json(text)


def evaluate_job(
    spec: Annotated[
        str | None,
        typer.Option(envvar=JOB_SPEC_ENV, help="The job spec (JSON).", show_default=False),
    ] = None,
    spec_file: Annotated[
        Path | None, typer.Option(envvar=JOB_SPEC_FILE_ENV, help="Read the job spec from here.")
    ] = None,
    policy: Annotated[
        str, typer.Option(envvar=POLICY_ENV, help="How the result names the policy.")
    ] = "external",
    shards: Annotated[int, typer.Option(envvar=SHARDS_ENV, min=1, help="Shards in the Job.")] = 1,
    index: Annotated[int, typer.Option(envvar=INDEX_ENV, min=0, help="This pod's shard.")] = 0,
    endpoint_dir: Annotated[
        Path, typer.Option(envvar=ENDPOINT_DIR_ENV, help="Where to listen (a shared volume).")
    ] = Path(ENDPOINT_DIR),
    video_dir: Annotated[
        Path | None,
        typer.Option(envvar=VIDEO_DIR_ENV, help="Write episode videos here (none: no videos)."),
    ] = None,
    trajectory_dir: Annotated[
        Path | None,
        typer.Option(
            envvar=TRAJECTORY_DIR_ENV,
            help="Write every episode's trajectory here, as this shard's parts (none: not kept).",
        ),
    ] = None,
) -> None:
    """Run the evaluation a Kubernetes Job describes; print the outcome for the worker."""
    if threading.current_thread() is threading.main_thread():  # not when called in a test
        signal.signal(signal.SIGTERM, _stop_now)
    try:
        plan = load_job(spec, spec_file).plan()
        if index >= shards:
            raise ValueError(f"shard index {index} is not below the shard count {shards}")
    except (OSError, ValueError) as exc:  # SuiteError and ValidationError are ValueErrors
        print(f"manieval evaluate-job: bad job spec: {exc}", file=sys.stderr)
        raise typer.Exit(2) from None
    document = run_job(
        plan,
        ExternalPolicy(policy),
        index=index,
        shards=shards,
        socket_dir=endpoint_dir,
        video_dir=video_dir,
        trajectory_dir=trajectory_dir,
    )
    sys.stderr.flush()
    write_document(document, sys.stdout)


def _stop_now(signum: int, _frame: object) -> None:
    """The pod is being deleted (a cancel, an eviction): stop at once. As a container's PID 1,
    Python would otherwise ignore SIGTERM and run on until the kubelet's SIGKILL."""
    os.write(2, b"manieval evaluate-job: stopped (SIGTERM)\n")
    os._exit(128 + signum)


if __name__ == "__main__":
    typer.run(evaluate_job)

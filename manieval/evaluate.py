"""`manieval evaluate`: score a policy on a suite from the terminal, with live progress."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text

from manieval import render
from manieval.errors import not_installed
from manieval.policy_output import FileOutput, LiveOutput, PolicyOutput, policy_output, shown

if TYPE_CHECKING:  # the evaluator (torch, SAPIEN) is imported when the command runs
    from evaluator.plan import EvaluationPlan
    from evaluator.results import Abort, EvaluationResult
    from evaluator.sources import PolicySource

SECRET_ENV = "MANIEVAL_SEED_SECRET"
console = Console(stderr=True, soft_wrap=True)  # error messages stay whole for grep and logs


def evaluate(
    policy: Annotated[
        Path | None, typer.Option(help="Policy directory containing policy.py.")
    ] = None,
    image: Annotated[
        str | None,
        typer.Option(
            help="Policy container image (a local tag or repo@sha256:...), run exactly as a "
            "submission is: no network, read-only, limits."
        ),
    ] = None,
    engine: Annotated[
        str | None,
        typer.Option(
            envvar="MANIEVAL_DOCKER_ENGINE_URL",
            help="Docker-API engine for --image [default: the engine of the local server's "
            "data directory (MANIEVAL_DATA_DIR) while it runs, else "
            "unix:///run/manieval/podman.sock].",
        ),
    ] = None,
    suite: Annotated[str, typer.Option(help="Suite name (bundled) or YAML path.")] = (
        "maniskill-core"
    ),
    phase: Annotated[str, typer.Option(help="Phase whose seeds to use.")] = "dev",
    tasks: Annotated[
        list[str] | None,
        typer.Option("--tasks", help="Only these tasks (repeat or comma-separate)."),
    ] = None,
    episodes: Annotated[
        int | None, typer.Option(min=1, help="Episodes per task (default: the suite's).")
    ] = None,
    workers: Annotated[int, typer.Option(min=1, max=64, help="Worker processes.")] = 1,
    condition: Annotated[
        list[str] | None, typer.Option("--condition", help="Only these conditions (repeatable).")
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the result document here.")
    ] = None,
    video: Annotated[
        Path | None,
        typer.Option(help="Record each task's first episode to mp4s in this directory."),
    ] = None,
    policy_output_to: Annotated[
        str | None,
        typer.Option(
            "--policy-output",
            metavar="live|FILE",
            help="Show what the policy prints (stdout and stderr) as it runs: 'live' prints "
            "each line on stderr after 'policy | '; anything else is a file to write it to. "
            "Whatever the outcome; without it, only an aborted run shows its last lines.",
        ),
    ] = None,
) -> None:
    """Evaluate a policy on a benchmark suite and print per-task success rates."""
    try:
        from evaluator.packages import pin
        from evaluator.plan import build_plan
        from evaluator.sources import PolicySourceError
        from evaluator.suite import SuiteError, load_suite
    except ModuleNotFoundError as exc:  # the participant's slim CLI has no simulator
        raise typer.Exit(not_installed("manieval evaluate", exc)) from None

    try:
        plan = build_plan(
            pin(load_suite(suite))[0],  # its task packages imported, their versions hashed
            phase,
            tasks=_split(tasks),
            conditions=_split(condition),
            episodes=episodes,
            secret=os.environ.get(SECRET_ENV, "").encode() or None,
            record_video=video is not None,
        )
        source = _source(policy, image, engine, gpus=plan.policy.gpus)
        echo = (
            None
            if policy_output_to is None
            else policy_output(policy_output_to, console, processes=workers)
        )
    except (SuiteError, PolicySourceError, ValueError, OSError) as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from None
    try:
        result = _run_with_progress(plan, source, workers=workers, video=video, echo=echo)
    finally:
        if echo is not None:
            echo.close()
    if result.abort is not None:
        _aborted(result.abort, shown_live=isinstance(echo, LiveOutput))
    else:
        render.stdout().print(result_table(result))
    if json_out is not None:
        json_out.write_text(result.model_dump_json(indent=2))
        console.print(f"result document written to {json_out}")
    if isinstance(echo, FileOutput):
        console.print(f"the policy's output written to {echo.path}")
    if result.abort is not None:
        raise typer.Exit(1)


def _aborted(abort: Abort, *, shown_live: bool) -> None:
    """Why the evaluation stopped, and the policy's last lines unless they were shown live:
    first and alone, since a table of zeros would read as a scored policy."""
    console.print(
        Text("evaluation aborted ", style="bold red") + Text(f"({abort.kind}): {abort.reason}")
    )
    if shown_live:
        console.print(Text("(the policy's output is above, after 'policy |')", style="dim"))
    elif abort.log_tail:
        console.print(Text("policy log tail:", style="dim"))
        for line in abort.log_tail[-2000:].split("\n"):
            console.print(Text(shown(line)), highlight=False)
    console.print("no score: the evaluation did not finish")


def _source(
    policy: Path | None, image: str | None, engine: str | None, *, gpus: int = 0
) -> PolicySource:
    from evaluator.sources import LocalDirectory, PolicySourceError

    if (policy is None) == (image is None):
        raise PolicySourceError("give exactly one of --policy DIR and --image REF")
    if policy is not None:
        return LocalDirectory(policy)
    assert image is not None
    # The worker's docker executor, so that a participant tests the exact submission path.
    # Imported here: only --image needs it, and the evaluator itself never depends on worker/.
    from worker.containers import DEFAULT_ENGINE_URL, ContainerImage, ExecutorError, pin_local
    from worker.containers import engine as connect

    url, looked = (engine, []) if engine else _default_engine(DEFAULT_ENGINE_URL)
    try:
        client = connect(url)
        pinned = pin_local(client, image)
        client.close()
        source = ContainerImage(pinned, submission=0, attempt=0, engine_url=url, gpus=gpus)
        source.pull()
    except ExecutorError as exc:
        raise PolicySourceError(str(exc)) from None
    except Exception as exc:  # the engine is unreachable or refused
        raise PolicySourceError(engine_unusable(url, looked, exc)) from None
    if pinned != image:
        console.print(f"{image} pinned as {pinned}")
    return source


def _default_engine(system_url: str) -> tuple[str, list[str]]:
    """The local demo's (or `manieval serve`'s) engine while it runs, else `system_url`."""
    from manieval.engines import default_engine
    from server.kit.settings import default_data_dir

    # Not `Settings()`: a participant has no server configuration (no secret key) to validate.
    data_dir = os.environ.get("MANIEVAL_DATA_DIR") or default_data_dir()
    return default_engine(Path(data_dir), system_url)


def engine_unusable(url: str, looked: list[str], exc: Exception) -> str:
    """Why --image cannot run: the engine tried, where a default was looked for, what to do."""
    where = f" (looked for an engine at {' then '.join(looked)})" if looked else ""
    return (
        f"cannot use the container engine at {url}{where}: {exc}. Start one (`manieval demo` "
        "or `manieval serve` starts Podman in its data directory; set MANIEVAL_DATA_DIR to that "
        "server's) or name one: --engine unix:///PATH/podman.sock or "
        "MANIEVAL_DOCKER_ENGINE_URL"
    )


def _split(values: list[str] | None) -> list[str] | None:
    if not values:
        return None
    return [part.strip() for value in values for part in value.split(",") if part.strip()]


def _run_with_progress(
    plan: EvaluationPlan,
    source: PolicySource,
    *,
    workers: int,
    video: Path | None,
    echo: PolicyOutput | None = None,
) -> EvaluationResult:
    from evaluator.evaluation import evaluate as run_evaluation

    runs = [(run.env_id, run.condition.name, len(run.seeds)) for run in plan.runs]
    shown = RunBars(console, runs) if console.is_terminal else RunLines(console, runs)
    with shown:
        return run_evaluation(
            plan,
            source,
            workers=workers,
            video_dir=video,
            on_episode=lambda index, episode: shown.episode(index, episode.success_once),
            on_output=echo,
        )


class RunLines:
    """Without a terminal: a line when a task and condition is done, with the time left."""

    def __init__(
        self,
        out: Console,
        runs: list[tuple[str, str, int]],
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.out = out
        self.runs = runs
        self.clock = clock
        self.total = sum(episodes for _, _, episodes in runs)
        self.done = [0] * len(runs)
        self.successes = [0] * len(runs)
        self.started = clock()

    def __enter__(self) -> RunLines:
        tasks = len({env_id for env_id, _, _ in self.runs})
        conditions = len({condition for _, condition, _ in self.runs})
        self.out.print(
            f"evaluating {self.total} episodes: {tasks} tasks under {conditions} conditions"
        )
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        return None

    def episode(self, index: int, success: bool) -> None:
        self.done[index] += 1
        self.successes[index] += success
        self.advanced(index)

    def advanced(self, index: int) -> None:
        env_id, condition, episodes = self.runs[index]
        if self.done[index] < episodes:
            return
        done = sum(self.done)
        left = render.time_left(self.clock() - self.started, done, self.total)
        self.out.print(
            Text(
                f"{env_id} ({condition}): {self.successes[index]}/{episodes} succeeded; "
                f"{done}/{self.total} episodes done" + (f", {left}" if left else "")
            )
        )


class RunBars(RunLines):
    """On a terminal: a bar per task and condition, and one for all, with the time left."""

    def __init__(self, out: Console, runs: list[tuple[str, str, int]]) -> None:
        super().__init__(out, runs)
        self.progress = Progress(
            TextColumn("{task.description}", markup=False),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[successes]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=out,
        )
        self.bars: list[TaskID] = []
        self.all: TaskID | None = None

    def __enter__(self) -> RunLines:
        self.progress.start()
        self.bars = [
            self.progress.add_task(f"{condition:>12} {env_id}", total=episodes, successes="")
            for env_id, condition, episodes in self.runs
        ]
        self.all = self.progress.add_task(f"{'all':>12}", total=self.total, successes="")
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.progress.stop()

    def advanced(self, index: int) -> None:
        ok = f"{self.successes[index]} ok"
        self.progress.update(self.bars[index], advance=1, successes=ok)
        assert self.all is not None
        self.progress.update(self.all, advance=1, successes=f"{sum(self.successes)} ok")


def result_table(result: EvaluationResult) -> Table:
    """Success rate (Wilson 95% interval) per task and condition."""
    table = Table(title=f"{result.suite.name} / {result.phase}: score {result.score:.3f}")
    table.add_column("task")
    for condition in result.conditions:
        table.add_column(condition.name, justify="right")
    rows: dict[str, list[str]] = {}
    for condition in result.conditions:
        for task in condition.tasks:
            rows.setdefault(task.env_id, []).append(
                f"{task.success_rate:.2f} [{task.ci_low:.2f}, {task.ci_high:.2f}]"
            )
    for env_id, cells in rows.items():
        table.add_row(env_id, *cells)
    table.add_row("[bold]score[/bold]", *(f"[bold]{c.score:.3f}[/bold]" for c in result.conditions))
    return table

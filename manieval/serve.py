"""`manieval serve` and `manieval demo`: the server composed with its worker, in one process."""

from __future__ import annotations

from typing import Annotated

import typer

from server.cli import console, migrated_sessions, settings

DEMO_EPISODES = 2
"""Episodes per task in `manieval demo`: with 3, its first leaderboard took 87-91 s on 2 cores
after the install, against the 90 s it must stay within (docs/capacity.md, "The demo")."""


def serve(
    host: Annotated[str, typer.Option(help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535)] = 8000,
    migrate: Annotated[
        bool,
        typer.Option(
            help="Bring the schema up to date first. With --no-migrate (several replicas, a "
            "migration Job) the server refuses to start on a schema that is not current."
        ),
    ] = True,
) -> None:
    """Run the service: the API and, on the embedded default, its worker (migrating the
    database first)."""
    from internal_api.logs import configure_logging
    from manieval.quiet import quiet_third_party
    from manieval.service import Service, end_process

    s = settings()
    configure_logging(s.log_format, s.log_level)
    if s.queue == "inline":  # the simulator runs in this process: its warnings, once each
        quiet_third_party(s.data_dir / "simulator.log")
    if migrate:
        sessions = migrated_sessions(s)
    else:
        from server.kit.db import make_engine, schema_problem, session_factory

        problem = schema_problem(s.resolved_database_url)
        if problem is not None:
            console.print(f"[red]cannot start:[/] {problem}")
            raise typer.Exit(3)
        sessions = session_factory(make_engine(s.resolved_database_url))
    from manieval.engines import embedded_engines

    engines = embedded_engines(s, host=host, port=port)
    service = Service(s, host=host, port=port, sessions=sessions, engines=engines)
    try:
        for problem in service.start_engines():
            console.print(f"[yellow]{problem}[/]")
    except KeyboardInterrupt:  # those started so far stop now, not with the process
        engines.stop()
        raise
    console.print(f"ManiEval on http://{host}:{port}  (data: {s.data_dir}, docs: /docs)")
    if engines.registry_domain is not None:
        console.print(f"registry: {engines.registry_domain}  (manieval push IMAGE --challenge ...)")
    service.run()
    end_process(0)


def demo(
    host: Annotated[str, typer.Option(help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535)] = 8000,
    episodes: Annotated[int, typer.Option(min=1, help="Episodes per task.")] = DEMO_EPISODES,
    exit_when_done: Annotated[
        bool, typer.Option(help="Stop once the example policies are evaluated.")
    ] = False,
) -> None:
    """Run the service locally with the example policies evaluated on the leaderboard."""
    import os
    import signal

    from manieval.demo import run_demo
    from manieval.service import end_process

    # SIGTERM stops the demo as Ctrl-C does: the service stops what runs and records it.
    signal.signal(signal.SIGTERM, signal.default_int_handler)

    os.environ.setdefault("MANIEVAL_DEV_MODE", "true")
    os.environ.setdefault("MANIEVAL_ALLOW_LOCAL_POLICIES", "true")
    os.environ.setdefault("MANIEVAL_COOKIE_SECURE", "false")
    os.environ.setdefault("MANIEVAL_INLINE_WORKERS", str(min(2, os.cpu_count() or 1)))
    try:
        code = run_demo(
            settings(), host=host, port=port, episodes=episodes, exit_when_done=exit_when_done
        )
    except KeyboardInterrupt:  # a second Ctrl-C while stopping: what still runs ends with us
        code = 130
    end_process(code)
    raise typer.Exit(code)

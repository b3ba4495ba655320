"""The simulator's warnings stay off the service's console: once each, in its log file."""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

from manieval.quiet import RENDERER_LOG_ENV, THIRD_PARTY_LOGGERS, quiet_third_party


@pytest.fixture
def restored() -> Iterator[None]:
    """Put back what quiet_third_party changes in this process."""
    shown = warnings.showwarning
    loggers = {
        name: (logging.getLogger(name).handlers[:], logging.getLogger(name).propagate)
        for name in THIRD_PARTY_LOGGERS
    }
    renderer = os.environ.get(RENDERER_LOG_ENV)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        yield
    warnings.showwarning = shown
    for name, (handlers, propagate) in loggers.items():
        logging.getLogger(name).handlers[:] = handlers
        logging.getLogger(name).propagate = propagate
    if renderer is None:
        os.environ.pop(RENDERER_LOG_ENV, None)


def warn_from(filename: str, message: str) -> None:
    """A warning as if raised by code in `filename`."""
    warnings.warn_explicit(message, UserWarning, filename, 12)


def test_third_party_warnings_go_to_the_log_file_once_and_ours_still_show(
    restored: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    shown: list[str] = []
    warnings.showwarning = lambda message, *_args, **_kwargs: shown.append(str(message))
    log = tmp_path / "demo.log"
    handler = quiet_third_party(log)
    maniskill = "/venv/site-packages/mani_skill/envs/sapien_env.py"
    for _ in range(3):
        warn_from(maniskill, "shader_dir argument will be deprecated")
    warn_from("/venv/site-packages/gymnasium/core.py", "env.seed is deprecated")
    logging.getLogger("mani_skill ").warning("robot is not in the task's list")
    logging.getLogger("mani_skill ").warning("robot is not in the task's list")
    warn_from("/work/main/server/app.py", "our own warning")
    handler.flush()
    err = capsys.readouterr().err
    assert "shader_dir" not in err
    assert "robot is not" not in err
    assert shown == ["our own warning"]  # shown as before: it is ours
    text = log.read_text()
    assert text.count("shader_dir argument will be deprecated") == 1
    assert text.count("env.seed is deprecated") == 1
    assert text.count("robot is not in the task's list") == 1
    assert os.environ[RENDERER_LOG_ENV] == "error"

"""Exit codes: scripts tell outcomes apart by them."""

from __future__ import annotations

from manieval.errors import STATE_CODES, ExitCode


def test_every_exit_code_is_distinct() -> None:
    assert len({code.value for code in ExitCode}) == len(ExitCode.__members__)


def test_only_succeeded_exits_zero_and_each_final_state_has_its_code() -> None:
    assert set(STATE_CODES) == {"succeeded", "failed", "timed_out", "error", "cancelled"}
    assert [s for s, code in STATE_CODES.items() if code == ExitCode.OK] == ["succeeded"]
    assert len(set(STATE_CODES.values())) == len(STATE_CODES)

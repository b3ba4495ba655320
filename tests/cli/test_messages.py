"""What the commands say when something ended badly or is empty: the state's own words."""

from __future__ import annotations

from pathlib import Path

from manieval.participant import empty_log_message


def test_an_empty_log_is_explained_by_the_submissions_state() -> None:
    assert empty_log_message(7, 1, "succeeded") == (
        "submission 7 (attempt 1) ended succeeded; its policy wrote nothing to stdout or stderr"
    )
    assert "yet" not in empty_log_message(7, 2, "failed")
    assert (
        empty_log_message(7, 1, "queued") == "submission 7 (attempt 1) has not started yet: no log"
    )
    assert empty_log_message(7, 1, "running") == (
        "no log for submission 7 (attempt 1) yet: its policy has written nothing so far"
    )


def test_a_failed_demo_says_what_to_do_next_for_each_way_of_failing() -> None:
    from manieval.demo import next_steps

    log = Path("/data/demo.log")
    crashed = "\n".join(next_steps(["failed", "failed"], log_path=log))
    assert "manieval evaluate --policy examples/policies/random" in crashed
    assert "demo.log" not in crashed
    assert "run manieval demo again" in crashed
    broken = "\n".join(next_steps(["error", "timed_out"], log_path=log))
    assert "not the policies' fault): see /data/demo.log" in broken
    assert "manieval evaluate" in broken
    assert "cancelled" in "\n".join(next_steps(["cancelled"], log_path=log))

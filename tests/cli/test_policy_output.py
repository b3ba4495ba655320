"""How `manieval evaluate --policy-output` shows the policy's output: lines the evaluator's
own cannot be mistaken for, and a file as the policy printed it."""

from __future__ import annotations

import io
from pathlib import Path

from rich.console import Console

from manieval.policy_output import LONGEST_LINE, FileOutput, LiveOutput, policy_output, shown


def console() -> tuple[Console, io.StringIO]:
    out = io.StringIO()
    return Console(file=out, width=200, force_terminal=False, soft_wrap=True), out


def test_control_characters_are_spelled_out_and_a_carriage_return_shows_what_it_leaves():
    assert shown("step 3: reward 0.5") == "step 3: reward 0.5"
    assert shown("\x1b[2J\x1b[Hevaluation aborted") == "\\x1b[2J\\x1b[Hevaluation aborted"
    assert shown("\u202eevil") == "\\u202eevil"  # a bidi override
    assert shown(" 10%|#   \r 20%|##  ") == " 20%|##  "
    assert shown("windows line\r") == "windows line"
    assert shown("a\tb") == "a\tb"


def test_each_line_is_printed_after_policy_once_whole_even_across_pieces():
    out, text = console()
    live = LiveOutput(out, processes=1)
    live(0, b"loading wei")
    live(0, b"ghts\nready\nno newline ")
    live(0, "caf\u00e9".encode()[:4])  # a character split between two pieces
    live(0, "caf\u00e9".encode()[4:])
    assert text.getvalue() == "policy | loading weights\npolicy | ready\n"
    live.close()
    assert text.getvalue().endswith("policy | no newline caf\u00e9\n")


def test_a_line_that_never_ends_is_shown_in_pieces():
    out, text = console()
    live = LiveOutput(out, processes=1)
    live(0, b"x" * (2 * LONGEST_LINE + 5))
    assert text.getvalue() == 2 * f"policy | {'x' * LONGEST_LINE}\n"
    live.close()
    assert text.getvalue().endswith("policy | xxxxx\n")


def test_several_policy_processes_are_numbered_and_their_lines_kept_apart():
    out, text = console()
    live = LiveOutput(out, processes=2)
    live(0, b"first ")
    live(1, b"second\n")
    live(0, b"half\n")
    assert text.getvalue() == "policy 2 | second\npolicy 1 | first half\n"


def test_a_file_holds_the_output_as_printed_or_by_process_when_several(tmp_path: Path):
    one = FileOutput(tmp_path / "one.log", processes=1)
    one(0, b"\x1b[1mbold\x1b[0m\nno newline")
    one.close()
    assert (tmp_path / "one.log").read_bytes() == b"\x1b[1mbold\x1b[0m\nno newline"
    two = policy_output(str(tmp_path / "two.log"), console()[0], processes=2)
    assert isinstance(two, FileOutput)
    two(1, b"b1\nb")
    two(0, b"a1\n")
    two.close()
    assert (tmp_path / "two.log").read_bytes() == b"[2] b1\n[1] a1\n[2] b\n"

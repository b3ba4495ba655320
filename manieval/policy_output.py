"""`manieval evaluate --policy-output`: the policy's own output, live or in a file, whatever
the evaluation's outcome.

The evaluator passes the output of each policy process on as it comes, bounded
(`evaluator.sources.OutputEcho`). Live, every line is printed on stderr after `policy | `, with
its control characters shown escaped: nothing a policy prints can pass for a line of the
evaluator's, move the cursor or redraw the progress bars. In a file, the output is kept as the
policy printed it.
"""

from __future__ import annotations

import codecs
from pathlib import Path
from typing import IO

from rich.console import Console
from rich.text import Text

LIVE = "live"
LONGEST_LINE = 4096
"""Characters of a line shown at once: a line that never ends is shown in pieces this long."""


def shown(line: str) -> str:
    """`line` as a terminal may print it: what a carriage return would leave visible, and every
    other control or format character (escape sequences, bidi overrides) spelled out."""
    line = line.removesuffix("\r").rpartition("\r")[2]
    return "".join(c if c.isprintable() or c == "\t" else _escaped(c) for c in line)


def _escaped(c: str) -> str:
    code = ord(c)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


class LiveOutput:
    """Prints each line of each policy process on `out` after `policy | ` (`policy N | ` when
    there are several)."""

    def __init__(self, out: Console, *, processes: int) -> None:
        self._out = out
        self._numbered = processes > 1
        self._decoders: dict[int, codecs.IncrementalDecoder] = {}
        self._partial: dict[int, str] = {}

    def __call__(self, shard: int, data: bytes) -> None:
        decoder = self._decoders.setdefault(
            shard, codecs.getincrementaldecoder("utf-8")(errors="replace")
        )
        text = self._partial.pop(shard, "") + decoder.decode(data)
        *lines, rest = text.split("\n")
        while len(rest) > LONGEST_LINE:
            lines.append(rest[:LONGEST_LINE])
            rest = rest[LONGEST_LINE:]
        for line in lines:
            self._print(shard, line)
        if rest:
            self._partial[shard] = rest

    def close(self) -> None:
        """Print what is left of unfinished lines."""
        for shard, decoder in self._decoders.items():
            rest = self._partial.pop(shard, "") + decoder.decode(b"", final=True)
            if rest:
                self._print(shard, rest)

    def _print(self, shard: int, line: str) -> None:
        label = f"policy {shard + 1} | " if self._numbered else "policy | "
        self._out.print(Text(label, style="dim") + Text(shown(line)), highlight=False)


class FileOutput:
    """Writes the policy's output to a file as it comes; with several policy processes, each
    line after `[N] `."""

    def __init__(self, path: Path, *, processes: int) -> None:
        self.path = path
        self._file: IO[bytes] = path.open("wb")
        self._numbered = processes > 1
        self._partial: dict[int, bytes] = {}

    def __call__(self, shard: int, data: bytes) -> None:
        if not self._numbered:
            self._file.write(data)
        else:
            *lines, rest = (self._partial.pop(shard, b"") + data).split(b"\n")
            for line in lines:
                self._file.write(b"[%d] %s\n" % (shard + 1, line))
            if rest:
                self._partial[shard] = rest
        self._file.flush()  # readable while the evaluation runs (`tail -f`)

    def close(self) -> None:
        """Write what is left of unfinished lines, and close the file."""
        for shard, rest in sorted(self._partial.items()):
            self._file.write(b"[%d] %s\n" % (shard + 1, rest))
        self._partial.clear()
        self._file.close()


PolicyOutput = LiveOutput | FileOutput


def policy_output(target: str, out: Console, *, processes: int) -> PolicyOutput:
    """`live`: on `out`; anything else: the file of that name (OSError if it cannot be made)."""
    if target == LIVE:
        return LiveOutput(out, processes=processes)
    return FileOutput(Path(target), processes=processes)

"""Run one command: parse its options, configure logging, run it, leave cleanly.

``safemimic COMMAND ...`` (:mod:`safemimic.cli`) and each service's own entry point
(``python -m services.X ...``, its ``__main__.py``) both come here, so a service runs the same
way with or without the ``safemimic`` package. A command module provides
``build_parser(parser) -> parser`` and ``run(args) -> int``; a refusal it raises on purpose
(:class:`~shared.errors.SafemimicError`: an invalid configuration, a missing certificate, a source
that cannot open, ...) ends the command with its message on one line and exit code 2, never a
traceback. A help text with paragraphs and examples uses :class:`ParagraphHelpFormatter`.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import os
import sys
import textwrap
from collections.abc import Callable, Sequence

from shared.errors import SafemimicError

LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"


class ParagraphHelpFormatter(argparse.HelpFormatter):
    """argparse's help, its description and epilog wrapped to the terminal paragraph by paragraph
    (blank lines kept), lines that start with a space (examples, commands) kept as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        paragraphs = []
        for paragraph in text.split("\n\n"):
            lines: list[str] = []
            for verbatim, group in itertools.groupby(paragraph.splitlines(), key=lambda line: line[:1].isspace()):
                if verbatim:
                    lines += [indent + line for line in group]
                else:
                    lines.append(textwrap.fill(" ".join(" ".join(group).split()), width,
                                               initial_indent=indent, subsequent_indent=indent))
            paragraphs.append("\n".join(lines))
        return "\n\n".join(paragraphs)


def run_command(
    name: str,
    build_parser: Callable[[argparse.ArgumentParser], argparse.ArgumentParser],
    run: Callable[[argparse.Namespace], int | None],
    argv: Sequence[str],
) -> int:
    """Parse ``argv`` with the command's parser (``prog`` ``safemimic NAME``), log at INFO, run it;
    its exit code (2 with ``safemimic NAME: message`` on stderr for a :class:`SafemimicError` it
    raises; 1, silently, when the reader of its output left). A Zenoh session close that hung (its router went away at the same moment) would keep
    the process alive: then the output is flushed and the process leaves at once."""
    parser = build_parser(argparse.ArgumentParser(prog=f"safemimic {name}"))
    args = parser.parse_args(list(argv))
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
    try:
        code = int(run(args) or 0)
    except SafemimicError as exc:
        print(f"safemimic {name}: {exc}", file=sys.stderr, flush=True)
        code = 2
    except BrokenPipeError:  # the reader left (`safemimic config | head`): no traceback (Python's recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 1
    bus = sys.modules.get("shared.bus")  # imported only by commands that opened a Zenoh session
    if bus is not None and bus.hung_closes():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code

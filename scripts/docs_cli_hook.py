"""mkdocs hook: fill docs/cli.md with `jaxcal --help` and every `jaxcal COMMAND --help`.

The marker `<!-- jaxcal-cli-help -->` in a page is replaced by one section per command, generated
in-process from `jaxcal.cli.build_parser()` (the parser the console script uses), so the page cannot
drift from the code. Help is wrapped at 100 columns whatever the terminal.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

MARKER = "<!-- jaxcal-cli-help -->"
SRC = Path(__file__).resolve().parents[1] / "src"


def _help_sections() -> str:
    if str(SRC) not in sys.path:
        sys.path.insert(0, str(SRC))
    os.environ["COLUMNS"] = "100"
    from jaxcal.cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")  # the subparsers action
    parts = ["## `jaxcal`", "", "```text", parser.format_help().rstrip(), "```", ""]
    for name in COMMANDS:
        text = sub.choices[name].format_help().rstrip()
        parts += [f"## `jaxcal {name}`", "", "```text", text, "```", ""]
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:  # mkdocs hook signature
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, _help_sections())

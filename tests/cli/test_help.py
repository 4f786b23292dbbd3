"""`comreg --help` and `comreg COMMAND --help` read as written: every paragraph of a command's
description (its docstring) and every option's help is reflowed as a whole, never broken where
the docstring's source lines happened to end."""

from __future__ import annotations

import inspect
import re

import click
import pytest
import typer
from typer.testing import CliRunner

from comreg_core.cli import app

#: Wide enough that no paragraph needs wrapping: each one must come out as one line.
WIDE = 2000


def _words(text: str) -> str:
    return " ".join(text.split())


def _paragraphs(text: str) -> list[str]:
    return [_words(p) for p in re.split(r"\n\s*\n", inspect.cleandoc(text)) if p.strip()]


def _commands() -> dict[str, click.Command]:
    group = typer.main.get_command(app)
    return {"": group, **group.commands}  # "" = comreg itself


def _help(name: str, columns: int) -> list[str]:
    result = CliRunner().invoke(app, [name, "--help"] if name else ["--help"],
                                env={"COLUMNS": str(columns), "TERMINAL_WIDTH": str(columns),
                                     "NO_COLOR": "1"}, color=False)
    assert result.exit_code == 0, result.output
    # rich draws the option tables with box characters: keep the text of each cell's line
    return [_words(line.strip(" │╭╮╰╯─")) for line in result.output.splitlines()]


def test_every_command_is_listed():
    names = set(_commands()) - {""}
    assert {"extract-ct", "simulate", "extract-us", "pretrain", "register", "evaluate", "report",
            "demo", "info", "batch", "live", "replay"} <= names


@pytest.mark.parametrize("name", sorted(_commands()))
def test_each_paragraph_of_the_description_is_one_line_on_a_wide_terminal(name):
    command = _commands()[name]
    lines = _help(name, WIDE)
    paragraphs = _paragraphs(command.help or "")
    assert paragraphs, f"'comreg {name}' has no description"
    for paragraph in paragraphs:
        assert paragraph in lines, (f"'comreg {name} --help' breaks this paragraph inside a "
                                    f"sentence:\n{paragraph}\n---\n" + "\n".join(lines))


@pytest.mark.parametrize("name", sorted(_commands()))
def test_each_option_help_is_one_line_on_a_wide_terminal(name):
    command = _commands()[name]
    lines = _help(name, WIDE)
    for param in command.params:
        text = "" if getattr(param, "hidden", False) else _words(getattr(param, "help", None) or "")
        if text:
            assert any(line.endswith(text) or f"{text} [" in line for line in lines), (
                f"'comreg {name} --help': the help of {param.name} is broken:\n{text}")


@pytest.mark.parametrize("name", sorted(_commands()))
def test_no_description_line_ends_mid_sentence_when_it_had_room(name):
    """At 100 columns a description line ends where the next word no longer fits, never early
    (an early end is a hard break left over from the docstring's source)."""
    columns = 100
    command = _commands()[name]
    lines = _help(name, columns)
    for paragraph in _paragraphs(command.help or ""):
        words = paragraph.split()
        # the lines of the output that hold this paragraph, in order
        start = next(i for i, line in enumerate(lines) if line and paragraph.startswith(line))
        shown, i = [], start
        while len(" ".join(shown).split()) < len(words):
            shown.append(lines[i])
            i += 1
        assert _words(" ".join(shown)) == paragraph
        for line, following in zip(shown, shown[1:]):
            room = columns - 2 - len(line)  # rich pads one space on either side
            assert len(following.split()[0]) + 1 > room, (
                f"'comreg {name} --help' ends a line early:\n{line}\n{following}")

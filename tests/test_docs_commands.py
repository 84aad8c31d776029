"""The docs' `sim2act` commands still parse: every one in a shell block of README.md and docs/ is read by
the CLI's own parser, and its campaign options (preset, config file, every --set) by the config loader,
without running anything; the prose's inline commands have each --flag checked. A renamed flag or config
field fails here, not in a reader's terminal."""

import argparse
import re
import shlex
from pathlib import Path

import pytest

from flows.cli import build_parser
from flows.cli.common import campaign_config

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCED_BLOCK = re.compile(r"^ *```(\w*)\n(.*?)^ *```", re.S | re.M)  # every block, so fences stay paired
SHELL = {"", "bash", "sh", "shell", "console"}
# Placeholders the docs write for values a reader picks (train-<key>, $seed, --iteration K, [--json]):
# each becomes a value the parser takes, so the flags around it are still checked.
PLACEHOLDER = re.compile(r"<[^<>\s]+>|\$\{?\w+\}?|(?<![\w.-])[A-Z](?![\w.=-])")
SET_PLACEHOLDER = re.compile(r"--set\s+<[^<>\s]+>")  # --set <recipe>: whichever field the reader sets
OPTIONAL = re.compile(r"\[(--[^\[\]]*)\]")  # usage notation: [--json]
REDIRECT = re.compile(r"\s\d?(?:>>?|<)&?\s*\S+")
SEPARATORS = {";", "&&", "||", "|", "&", "(", ")", "do", "then"}
WRAPPERS = {"nohup", "setsid", "time", "exec", "nice"}


def shell_lines(block: str) -> list[str]:
    """The block's command lines: continuations joined, a quote that spans lines kept in one."""
    lines, pending = [], ""
    for line in re.sub(r"\\\n", " ", block).splitlines():
        pending = f"{pending}\n{line}" if pending else line
        try:
            shlex.split(pending, comments=True)
        except ValueError:  # an open quote (a SQL statement over several lines): read on
            continue
        lines.append(pending)
        pending = ""
    return lines


def sim2act_argv(line: str) -> list[list[str]]:
    """The arguments of each `sim2act` invocation on a shell line (after env assignments and wrappers)."""
    line = OPTIONAL.sub(r"\1", REDIRECT.sub(" ", PLACEHOLDER.sub("1", SET_PLACEHOLDER.sub(" ", line))))
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|()")
    lexer.whitespace_split = True
    segments = [[]]
    for word in lexer:  # quoted words (SQL with its `||`) stay whole; separators split commands
        if word in SEPARATORS:
            segments.append([])
        else:
            segments[-1].append(word)
    found = []
    for words in segments:
        while words and (re.fullmatch(r"\w+=\S*", words[0]) or words[0] in WRAPPERS):
            words = words[1:]
        if words and Path(words[0]).name == "sim2act":
            found.append(words[1:])
    return found


def doc_commands() -> list[tuple[str, list[str]]]:
    return [(f"{doc.relative_to(ROOT)}: {' '.join(argv)[:80]}", argv)
            for doc in DOCS for language, block in FENCED_BLOCK.findall(doc.read_text()) if language in SHELL
            for line in shell_lines(block) for argv in sim2act_argv(line)]


DOC_COMMANDS = doc_commands()  # read once: the cases below and the check that there are enough of them


def test_the_docs_hold_enough_commands_to_check():
    """The extraction itself works: the docs show dozens of commands, `run` and `report` among them."""
    commands = [argv for _, argv in DOC_COMMANDS]
    assert len(commands) >= 50
    assert {"run", "report", "sql", "export", "bench"} <= {argv[0] for argv in commands if argv}


def _command_parser(parser: argparse.ArgumentParser, words: list[str]) -> argparse.ArgumentParser:
    """The (sub)command's own parser the words name: `bench rl ...` -> bench's rl."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and words and words[0] in action.choices:
            return _command_parser(action.choices[words[0]], words[1:])
    return parser


def test_every_flag_the_prose_names_exists():
    """Inline commands in the prose (`sim2act shadow --execution receding`) are fragments, not whole
    commands: each --flag they name is checked against its command's options."""
    parser, unknown, checked = build_parser(), [], 0
    for doc in DOCS:
        prose = FENCED_BLOCK.sub("", doc.read_text()).replace("\n", " ")
        for span in re.findall(r"`(sim2act [^`]+)`", prose):
            words = span.split()[1:]
            options = {option for action in _command_parser(parser, words)._actions for option in action.option_strings}
            for flag in (word.split("=")[0].rstrip(".,;:)") for word in words if word.startswith("--")):
                checked += 1
                if flag not in options:
                    unknown.append(f"{doc.relative_to(ROOT)}: {flag} in `{span}`")
    assert checked >= 50 and not unknown, unknown


@pytest.mark.parametrize("where, argv", DOC_COMMANDS, ids=lambda value: value if isinstance(value, str) else "")
def test_a_documented_command_parses(where, argv, monkeypatch):
    monkeypatch.chdir(ROOT)  # the docs' paths (docs/quality/*.yaml) are from the repository's root
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exit:
        pytest.fail(f"{where}: the CLI rejects it (exit {exit.code})")
    if hasattr(args, "preset") and hasattr(args, "set"):
        if args.config is not None and not args.config.exists():
            args.config = None  # the reader's own file (my.yaml): its --set fields are still checked
        campaign_config(args)

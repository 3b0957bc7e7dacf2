"""README.md stays a user's README: short enough to read in one sitting, in sentences a reader
can hold, linking only documents that exist, and showing `leco` commands the command line
accepts. The measures are the ones the README was written to (nerfstudio's README is about
2,000 words)."""

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
MAX_LINES, MAX_WORDS, MAX_SENTENCE_WORDS = 250, 2000, 40

FENCE = re.compile(r"^```.*?^```", re.M | re.S)
SENTENCE_END = re.compile(r"(?<=[.!?])\s+")


def words(text: str) -> list[str]:
    """Whitespace-separated tokens holding a letter or a digit (a table's pipes are not words)."""
    return [token for token in text.split() if re.search(r"\w", token)]


def sentences(text: str) -> list[str]:
    """The prose outside code blocks, one entry per sentence: a paragraph, list item, heading or
    table row is cut at each full stop, question or exclamation mark that a space follows."""
    prose = FENCE.sub("", text)
    units, current = [], []
    for line in prose.splitlines():
        starts_unit = not line.strip() or line.lstrip().startswith(("|", "#", "- ", "* ", "<!--"))
        if starts_unit and current:
            units.append(" ".join(current))
            current = []
        if line.strip():
            current.append(line.strip())
        if line.lstrip().startswith(("|", "#")):  # a row or a heading is a unit of its own
            units.append(" ".join(current))
            current = []
    units.append(" ".join(current))
    return [s for unit in units for s in SENTENCE_END.split(unit) if words(s)]


def longest(text: str) -> tuple[int, str]:
    return max((len(words(s)), s) for s in sentences(text))


def test_the_rules_measure_what_they_say():
    text = "# Title\n\nOne two three. Four five!\n\n| a | b |\n|---|---|\n\n```\nsix seven\n```\n"
    assert len(words(text)) == 10  # code counts as words, pipes and dashes do not
    assert sentences(text) == ["# Title", "One two three.", "Four five!", "| a | b |"]
    assert longest("A b c d. E f.") == (4, "A b c d.")


def test_the_readme_is_short():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_LINES
    assert len(words(text)) <= MAX_WORDS


def test_no_sentence_in_the_readme_runs_over_forty_words():
    count, sentence = longest(README.read_text())
    assert count <= MAX_SENTENCE_WORDS, f"{count} words: {sentence}"


def test_every_document_the_readme_links_exists():
    links = re.findall(r"\]\(([^)#\s]+)", README.read_text())
    local = [link for link in links if "://" not in link]
    assert "docs/METHODS.md" in local and "LICENSE" in local
    assert [link for link in local if not (ROOT / link).exists()] == []


def leco_commands(text: str) -> list[list[str]]:
    """Each `leco` command line in the README's bash blocks, as its arguments."""
    commands = []
    for block in re.findall(r"^```bash\n(.*?)^```", text, re.M | re.S):
        for line in block.replace("\\\n", " ").splitlines():
            argv = shlex.split(line, comments=True)
            while argv and argv[-1] == "&":
                argv.pop()
            if argv and argv[0].endswith("bin/leco"):
                commands.append(argv[1:])
    return commands


def test_every_leco_command_in_the_readme_is_one_the_command_line_accepts():
    from cli.main import build_parser

    commands = leco_commands(README.read_text())
    assert len(commands) >= 6
    parser = build_parser()
    for argv in commands:
        try:
            parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"`leco {shlex.join(argv)}` is refused by the command line")

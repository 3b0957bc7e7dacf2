"""docs/PROFILES.md is exactly what `leco settings --markdown` prints, so it cannot go stale: a
change of a default, a description or a section shows here until the file is rendered again."""

import json
from pathlib import Path

from cli.main import main
from cli.settings import escape, markdown
from model.profiles import PROFILES, settings

DOC = Path(__file__).resolve().parents[2] / "docs" / "PROFILES.md"


def test_docs_profiles_md_is_the_output_of_leco_settings_markdown(capsys):
    assert main(["settings", "--markdown"]) == 0
    printed = capsys.readouterr().out
    assert DOC.read_text() == printed, (
        "docs/PROFILES.md is stale: run `leco settings --markdown > docs/PROFILES.md`"
    )


def test_every_key_has_a_row_with_its_value_in_each_profile():
    text = markdown()
    rows = {}
    for line in text.splitlines():
        if line.startswith("| `"):
            key, *cells = line[2:-2].split(" | ")
            rows[key.strip("`")] = cells
    for name, column in (("smoke", 0), ("cpu", 1), ("paper", 2)):
        for key, value, description in settings(PROFILES[name]):
            assert rows[key][column].strip("*") == f"`{json.dumps(value)}`", (name, key)
            assert rows[key][3] == escape(description), key
    assert rows["guided.dilate"][:3] == ["`0`", "**`1`**", "`0`"]  # cpu's own value in bold
    assert rows["network.num_experts"][:3] == ["`2`", "`8`", "`8`"]  # as the paper's: plain


def test_a_prefix_keeps_only_its_sections_and_a_cell_stays_one_line():
    text = markdown("prop.")
    assert "## `prop`" in text and "## `guided`" not in text and "`guided.split`" not in text
    assert escape("a | b\n  c") == "a \\| b c"

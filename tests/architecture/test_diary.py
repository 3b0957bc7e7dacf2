"""README.md, docs/ and the code say what is true now: no authoring session, no "fast day", no
issue number used as section logic. History lives in git, CHANGELOG.md and docs/EXPERIMENTS.md
(a dated row per lever), so a reader never has to know which day a sentence was written on."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ORDINAL = (
    r"(?:first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth"
    r"|thirteenth|fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|twentieth"
    r"|twenty-\w+|thirtieth|thirty-\w+|\d+(?:st|nd|rd|th))"
)
DIARY = {
    "a session ordinal": re.compile(rf"\b{ORDINAL}(?:\W+\w+){{0,3}}?\W+sessions?\b", re.I),
    "a session number": re.compile(r"\bsessions?\s+#?\d+", re.I),
    "a day phrase": re.compile(
        r"\b(?:fast|faster|fastest|slow|slower|slowest|slowish|medium-speed)\s+day\b"
        r"|\bthat day\b|\bthe day before\b|\bthe day's\b|\bon the day\b",
        re.I,
    ),
    "an issue number": re.compile(r"\bissues?\s*#?\d+|(?<![\w&/])#\d{1,4}\b", re.I),
}
CODE = ("model", "workers", "service", "bench", "cli")


def read_by_people() -> list[Path]:
    docs = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]
    docs += sorted((ROOT / "docs" / "results").glob("*.json"))
    docs += sorted((ROOT / "deploy").rglob("*.md"))
    code = [p for package in CODE for p in sorted((ROOT / package).rglob("*.py"))]
    code += sorted((ROOT / "bench" / "recipes").glob("*"))
    return [p for p in docs + code if p.is_file()]


def offences(text: str) -> list[str]:
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for what, pattern in DIARY.items():
            match = pattern.search(line)
            if match:
                found.append(f"{number}: {what}: {match.group(0)!r}")
    return found


@pytest.mark.parametrize("sample", ["the twenty-seventh session's fast day", "issue 16", "#35"])
def test_the_rule_catches_a_diary_phrase(sample):
    assert offences(f"Measured on {sample}.")


@pytest.mark.parametrize(
    "sample", ["RaySession", "one session of the database", "2026-11-28", "step 1,500", "&#39;"]
)
def test_the_rule_leaves_plain_words_alone(sample):
    assert offences(f"It uses {sample}.") == []


def test_readme_docs_and_code_read_as_now_not_as_a_diary():
    found = {
        str(path.relative_to(ROOT)): hits
        for path in read_by_people()
        if (hits := offences(path.read_text(errors="replace")))
    }
    assert found == {}, "\n".join(f"{p}: {h[:5]}" for p, h in found.items())

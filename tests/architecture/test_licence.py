"""One licence, said the same way everywhere: the Apache-2.0 text in LICENSE, its SPDX name in
pyproject.toml's metadata and in CITATION.cff, which also cites the paper the code implements."""

import tomllib
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]


def test_the_licence_is_apache_2_0_in_every_place_that_declares_it():
    text = (ROOT / "LICENSE").read_text()
    assert text.split()[:4] == ["Apache", "License", "Version", "2.0,"]
    assert "END OF TERMS AND CONDITIONS" in text
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "Apache-2.0" and project["license-files"] == ["LICENSE"]
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert citation["license"] == "Apache-2.0"


def test_the_citation_file_cites_the_software_and_prefers_the_paper():
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert citation["cff-version"] == "1.2.0" and citation["type"] == "software"
    assert citation["message"] and citation["authors"] and citation["title"]
    paper = citation["preferred-citation"]
    assert paper["title"].startswith("LeCO-NeRF: Learning Compact Occupancy")
    assert {r["title"].split(":")[0] for r in citation["references"]} >= {
        "Switch-NeRF",
        "Instant Neural Graphics Primitives with a Multiresolution Hash Encoding",
    }

"""docs/reference.md is made from the parser, the control commands' declarations and the config schemas
(hmdrt.cli.reference): it must read as they make it now, and its help texts as `hmdrt ... --help` prints them."""

from __future__ import annotations

import difflib
import os
import subprocess
import sys
from pathlib import Path
from typing import Annotated

import msgspec
import pytest

from hmdrt.cli import reference

DOC = Path(__file__).parent.parent / "docs" / "reference.md"


def test_docs_reference_is_what_the_parser_the_commands_and_the_configs_make(monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")  # the reference wraps at its own width, whatever the terminal's
    made, written = reference.reference(), DOC.read_text()
    if made != written:
        diff = "".join(difflib.unified_diff(written.splitlines(True), made.splitlines(True), "written", "made", n=1))
        pytest.fail(
            f"docs/reference.md differs from what the parser, the control commands and the config schemas make; "
            f"run `{reference.COMMAND}` (and write the prose in hmdrt/cli/reference_text.py):\n{diff[:3000]}",
            pytrace=False,
        )
    assert os.environ["COLUMNS"] == "120"


@pytest.mark.parametrize("words", [["--help"], ["ctl", "--help"], ["export", "perfetto", "--help"]])
def test_the_help_in_the_reference_is_what_hmdrt_prints(words):
    printed = subprocess.run(
        [sys.executable, "-m", "hmdrt", *words],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "COLUMNS": str(reference.WIDTH)},
    )
    assert printed.returncode == 0, printed.stderr
    assert f"```\n{printed.stdout.rstrip()}\n```" in DOC.read_text()


def test_every_subcommand_and_config_key_is_in_the_reference():
    text = DOC.read_text()
    for words, _ in reference.parsers(reference.build_parser()):
        assert not words or f"\n### hmdrt {words}\n" in text
    for section in ("[display]", "[[drivers]]", "[security]", "[output]", "[run]", "[[traces]]", "[[methods]]"):
        assert f"\n### {section}\n" in text
    assert "| `set` | `method`: " in text and "| `tail_window` | integer (1 to 10,000) | `300` |" in text


def test_a_config_key_without_a_meaning_or_a_meaning_without_a_key_stops_the_reference():
    class Toy(msgspec.Struct):
        explained: int = 1
        described: Annotated[float, msgspec.Meta(ge=0, description="its own words")] = 0.5
        new_key: str = ""

    meanings = {"explained": "explained here"}
    with pytest.raises(reference.Unexplained, match="config key new_key has no meaning: add one to hmdrt/cli"):
        reference._config(Toy, meanings, {})
    made = "\n".join(reference._config(Toy, {**meanings, "new_key": "now explained"}, {}))
    assert "| `described` | number (at least 0) | `0.5` | its own words |" in made
    with pytest.raises(reference.Unexplained, match="explains config keys that are no more: gone"):
        reference._config(Toy, {**meanings, "new_key": "x", "gone": "y"}, {})

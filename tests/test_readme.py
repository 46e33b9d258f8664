"""The README a new user reads first: it opens with exactly the two commands, and every file and
command it points at exists."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEXT = (ROOT / "README.md").read_text()


def test_it_opens_with_exactly_the_two_commands():
    first = re.search(r"```sh\n(.*?)```", TEXT, re.S).group(1).strip().splitlines()
    assert [ln.split("#")[0].strip() for ln in first] == ["sh run.sh demo", "sh run.sh test"]
    assert TEXT.index("```sh") < TEXT.index("\n## ")  # before anything else


def test_every_file_it_names_exists():
    for path in set(re.findall(r"`((?:deploy|docs|protocol|clients|server)/[\w./-]+|[A-Z]+\.md)`", TEXT)):
        assert (ROOT / path).exists(), path
    for name in set(re.findall(r"`(?:deploy/configs/)?([\w-]+\.toml)`", TEXT)) - {"pyproject.toml"}:
        assert (ROOT / "deploy" / "configs" / name).exists(), name


def test_every_subcommand_it_shows_exists():
    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "--help"], capture_output=True, text=True,
                         timeout=120).stdout
    for cmd in set(re.findall(r"hapticproxy (\w+)", TEXT)) - {"is", "closes"}:
        assert f" {cmd} " in out or f"\n    {cmd}" in out or cmd in out.split(), cmd

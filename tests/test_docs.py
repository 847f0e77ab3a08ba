"""The docs hold together: links and anchors resolve, paths named in them exist, README stays
a front door (≤ 400 lines, its two set-up commands first, the same ones CI and the image run),
and the configuration page is the one generated from ``Settings``."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "CHANGELOG.md",
                *(ROOT / "docs").rglob("*.md")])
RUN_CMD = 'pip install ".[service]" && swarmloc serve --demo'
TEST_CMD = 'sh tests/install-system-deps.sh && pip install -e ".[dev]" && python -m pytest -q'

_FENCE = re.compile(r"^(```+|~~~+)[^\n]*\n(.*?)^\1[ \t]*$", re.M | re.S)
_INLINE_CODE = re.compile(r"`+[^`\n]*`+")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t#]*$", re.M)
_PATH = re.compile(r"`((?:service|client|tests|deploy|docs)/[A-Za-z0-9_./-]+)`")


def _prose(text: str) -> str:
    """The text without fenced blocks and inline code (links there are examples)."""
    return _INLINE_CODE.sub("", _FENCE.sub("", text))


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: markup dropped, lower case, punctuation removed,
    spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links keep their text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "").replace("*", "")
    text = re.sub(r"(?<!\w)_|_(?!\w)", "", text)
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out: set[str] = set()
    for heading in _HEADING.findall(_FENCE.sub("", path.read_text())):
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def test_slug_follows_github() -> None:
    assert slug("The papers (`swarmloc paper`)") == "the-papers-swarmloc-paper"
    assert slug("Fast exact matcher (uint8 descriptors)") == "fast-exact-matcher-uint8-descriptors"
    assert slug("ROS 2 / rosbag2") == "ros-2--rosbag2"
    assert slug("`SWARMLOC_HOST`, flags") == "swarmloc_host-flags"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    broken = []
    for target in _LINK.findall(_prose(page.read_text())):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert broken == [], broken


@pytest.mark.parametrize("page", [p for p in PAGES if p.name != "CHANGELOG.md"],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_named_repository_paths_exist(page: Path) -> None:
    """`service/...` and the like, named in backticks, are files or folders of this tree
    (the changelog names old paths on purpose)."""
    missing = [p for p in _PATH.findall(page.read_text())
               if not (ROOT / p.rstrip(".,:;")).exists() and not re.search(r"[*{<]", p)]
    assert missing == [], missing


def test_readme_is_a_front_door() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 400
    blocks = [body.strip() for _, body in _FENCE.findall(text)]
    assert blocks[:2] == [RUN_CMD, TEST_CMD]
    # nothing but a title and prose before the first command
    assert text.index("```") < 1500


def test_ci_and_the_image_run_the_readme_commands() -> None:
    """.ci/run's command is README's test command verbatim; the Docker image's command is
    the `serve` of README's run command (through the service's own entry point)."""
    ci = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines()
          if ln.strip() and not ln.lstrip().startswith("#")]
    assert ci[-1] == TEST_CMD
    docker = (ROOT / "Dockerfile").read_text()
    cmd = re.search(r"^CMD (\[.*\])$", docker, re.M)
    assert cmd is not None
    serve_in_readme = shlex.split(RUN_CMD.split("&&")[-1])[1:]
    assert json.loads(cmd.group(1))[1:] == serve_in_readme


def test_configuration_page_is_generated_from_settings() -> None:
    from client.lab import docs_config

    assert docs_config.PAGE.read_text() == docs_config.render(), (
        "docs/reference/configuration.md is out of date: python -m client.lab.docs_config "
        "--write")

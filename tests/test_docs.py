"""The documentation holds together: links and anchors resolve, every script and flag the docs
name exists, docs/results.md gives each table its command, and the README and docs/results.md
define the scores alike. Static: reads files only, runs nothing."""

from __future__ import annotations

import re

import pytest

from tests.helpers import REPO

DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path) -> set[str]:
    return {slug(h) for h in re.findall(r"^#+ (.*)$", path.read_text(), flags=re.MULTILINE)}


def section(text: str, heading: str) -> str:
    """The text under ``## heading`` up to the next heading of level 2 or above."""
    start = text.index(f"## {heading}\n")
    end = re.search(r"^#{1,2} ", text[start + 3:], flags=re.MULTILINE)
    return text[start:start + 3 + end.start()] if end else text[start:]


@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.name)
def test_relative_links_and_their_anchors_resolve(path):
    for target in re.findall(r"\]\(([^)\s]+)\)", path.read_text()):
        if re.match(r"[a-z]+://", target):
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        assert dest.exists(), f"{path.name}: link to missing {target}"
        if anchor and dest.suffix == ".md":
            assert anchor in anchors(dest), f"{path.name}: no heading for #{anchor} in {dest.name}"


@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.name)
def test_every_script_and_flag_named_exists(path):
    text = path.read_text()
    for name in set(re.findall(r"scripts/(\w+)\.py", text)):
        assert (REPO / "scripts" / f"{name}.py").is_file(), f"{path.name}: scripts/{name}.py is gone"
    for line in text.splitlines():  # flags of `python scripts/X.py ...` commands, up to a comment
        for name, args in re.findall(r"python scripts/(\w+)\.py([^`#]*)", line):
            source = (REPO / "scripts" / f"{name}.py").read_text()
            for flag in re.findall(r"(?<![\w-])(--[a-z][\w-]*)", args):
                assert f'"{flag}"' in source, f"{path.name}: scripts/{name}.py has no {flag}"


def test_the_readme_links_results_and_reference():
    readme = (REPO / "README.md").read_text()
    assert "(docs/results.md" in readme and "(docs/reference.md" in readme


def test_every_results_table_says_how_it_was_measured():
    text = (REPO / "docs" / "results.md").read_text()
    blocks = re.split(r"^(?=#{2,3} )", text, flags=re.MULTILINE)
    for block in blocks:
        if re.search(r"^\|---", block, flags=re.MULTILINE):
            heading = block.splitlines()[0]
            assert ("Command" in block or "command not recorded" in block.lower()), heading


def test_the_readme_defines_the_detail_correlation_with_the_codes_constants():
    from flamerecon.evaluate.metrics import DETAIL_REFERENCE_PX, DETAIL_SIGMA_PX

    scores = section((REPO / "README.md").read_text(), "Scores")
    for term in ("PSNR", "Black-image floor", "SSIM", "Detail correlation", "detail_silhouette",
                 "eval/heldout_detail", "held-out detail", f"DETAIL_SIGMA_PX={DETAIL_SIGMA_PX:g}",
                 f"DETAIL_REFERENCE_PX={DETAIL_REFERENCE_PX}"):
        assert term in scores, term
    assert "../README.md#scores" in section((REPO / "docs" / "results.md").read_text(), "Scores")


def test_the_calibration_options_are_documented():
    readme = (REPO / "README.md").read_text()
    for term in ("calibration.gauge", "similarity", "calibration.rig", "rig-calibrated", "strict",
                 "leave_one_out.py --rig", "--loo --rig"):
        assert term in readme, term
    results = (REPO / "docs" / "results.md").read_text()
    assert "## Self-calibration protocols (strict, rig-calibrated)\n" in results


def test_the_readme_is_a_manual_a_newcomer_reads_in_minutes():
    lines = (REPO / "README.md").read_text().splitlines()
    # 300: room for a short section per capability (full resolution, the viewer, confidence, flow)
    assert len(lines) < 300, f"README.md has {len(lines)} lines; measured results go to docs/results.md"

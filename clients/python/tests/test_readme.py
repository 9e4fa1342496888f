"""The SDK's README links only inside the repository (no absolute paths, nothing above the
repository root) and every relative link names a file or folder that exists."""

from __future__ import annotations

import re
from pathlib import Path

CLIENT_DIR = Path(__file__).resolve().parents[1]
REPO = CLIENT_DIR.parents[1]
README = CLIENT_DIR / "README.md"


def test_the_sdk_readme_links_stay_in_the_repository():
    text = README.read_text()
    assert "/work/" not in text and "shared/" not in text
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert links, "the README links the .proto and the package's modules"
    for link in links:
        if re.match(r"[a-z]+://", link):
            continue
        target = (README.parent / link.split("#")[0]).resolve()
        assert target.is_relative_to(REPO), f"{link} leaves the repository"
        assert target.exists(), f"{link} names nothing"

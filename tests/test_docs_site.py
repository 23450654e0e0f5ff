"""The documentation site (``mkdocs.yml`` over ``docs/``) builds with warnings as errors — every link
between pages resolves, every page is in the navigation — and a tutorial's code runs as written."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_site_builds_strictly_with_every_page_in_the_nav(tmp_path):
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                        "-d", str(tmp_path / "site")], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "not included in the \"nav\"" not in r.stderr, r.stderr
    assert (tmp_path / "site" / "tutorials" / "sysid-loop" / "index.html").is_file()
    pages = {p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md")}
    nav = set(re.findall(r":\s*([\w./-]+\.md)\s*$", (ROOT / "mkdocs.yml").read_text(), re.M))
    assert pages == nav, f"pages not in the nav: {sorted(pages - nav)}; nav entries without a page: {sorted(nav - pages)}"


def test_the_compose_tutorial_runs_as_written(tiny_dataset, tmp_path, monkeypatch):
    """docs/tutorials/compose-policy.md: its Python blocks, in order, on the session's tiny dataset
    (the tutorial builds it at data/tiny)."""
    text = (ROOT / "docs" / "tutorials" / "compose-policy.md").read_text()
    code = "\n".join(re.findall(r"```python\n(.*?)```", text, re.S)).replace('"data/tiny"', repr(str(tiny_dataset)))
    monkeypatch.chdir(tmp_path)
    scope = {"__name__": "tutorial"}
    exec(compile(code, "compose-policy.md", "exec"), scope)
    assert scope["result"]["iterations"] == 4 and Path(scope["result"]["policy"]).is_file()
    assert scope["rollout"].batch_size[0] == 4

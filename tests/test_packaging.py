"""Set-up and docs stay consistent: pinned dependencies, the README's commands, the docs nav.

Cheap checks without network or a docs build (CI builds the site with `scripts/docs.sh`).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _canon(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(req: str) -> str:
    return _canon(re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", req.strip()).group(0))


def test_constraints_pin_every_declared_dependency():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = {_requirement_name(r) for r in project["dependencies"]}
    for extra in ("test", "docs"):
        declared |= {_requirement_name(r) for r in project["optional-dependencies"][extra]}
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, sep, version = line.partition("==")
            assert sep and version, f"constraints.txt: not an exact pin: {line!r}"
            pins[_canon(name)] = version
    assert "jaxcal" not in pins
    missing = sorted(declared - set(pins))
    assert not missing, f"declared in pyproject.toml but not pinned in constraints.txt: {missing}"


def test_setup_installs_with_the_constraints_and_stamps_their_hash():
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    assert re.search(r"pip install .*-c constraints\.txt", setup)
    assert re.search(r"want=.*constraints\.txt.*sha256sum", setup)


def test_readme_starts_with_the_two_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert lines[0] == "```bash"
    assert lines[1].startswith("bash scripts/demo.sh")
    assert lines[2].startswith("bash scripts/test.sh")
    assert lines[3] == "```"


def test_ci_runs_the_tests_first_then_lint_then_the_docs():
    steps = [s for s in (ROOT / ".ci" / "run").read_text().splitlines() if s.startswith("bash ")]
    assert steps == ["bash scripts/test.sh", "bash scripts/lint.sh", "bash scripts/docs.sh"]


def _nav_files(node):
    if isinstance(node, str):
        yield node
    elif isinstance(node, list):
        for item in node:
            yield from _nav_files(item)
    elif isinstance(node, dict):
        for value in node.values():
            yield from _nav_files(value)


def test_docs_nav_pages_exist():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    docs = ROOT / config.get("docs_dir", "docs")
    pages = list(_nav_files(config["nav"]))
    assert "benchmarks/index.md" in pages and "cli.md" in pages
    missing = [p for p in pages if not (docs / p).is_file()]
    assert not missing, missing


def test_cli_page_documents_every_command():
    import importlib.util

    path = ROOT / "scripts" / "docs_cli_hook.py"
    spec = importlib.util.spec_from_file_location("docs_cli_hook", path)
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = hook.on_page_markdown("# CLI\n\n" + hook.MARKER + "\n", None, None, None)
    from jaxcal.cli import COMMANDS

    assert hook.MARKER not in page
    for name in COMMANDS:
        n = re.escape(name)
        assert re.search(rf"^## `jaxcal {n}`\n\n```text\nusage: jaxcal {n} ", page, re.M), name

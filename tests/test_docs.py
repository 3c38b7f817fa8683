"""The README and the documentation site: built, linked, generated from the code, runnable.

- the site builds with ``mkdocs build --strict`` (MkDocs is a dev dependency: the test fails,
  never skips, without it) and every internal link and anchor of the built pages resolves
  (no network: external links are not followed);
- the generated reference holds every CLI flag, REST route and machine-file field, each
  enumerated here from the code independently of the generator (``docs/hooks/reference.py``);
- every code block marked runnable in the README and the pages prints what the page shows
  (``docs/scripts/runnable.py``: numbers within 1 % or one unit of the last digit printed,
  run times not compared);
- the README stays short, with the figure and the Quickstart's two commands.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
import typing
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _module(path: Path):
    """A script of docs/ as a module (``docs_<stem>``)."""
    name = f"docs_{path.stem}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name]


runnable = _module(ROOT / "docs" / "scripts" / "runnable.py")


def _nav_files(nav) -> list[str]:
    out = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        out += _nav_files(value) if isinstance(value, list) else [value]
    return out


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site, built as CI builds it."""
    try:
        import mkdocs  # noqa: F401
        import yaml
    except ImportError as err:
        pytest.fail(f"MkDocs is not installed ({err}): pip install -e '.[dev]'", pytrace=False)
    config = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=yaml.BaseLoader)
    generated = {"reference/cli.md", "reference/rest.md", "reference/machine-file.md",
                 "reference/python.md", "changelog.md"}
    missing = [f for f in _nav_files(config["nav"])
               if f not in generated and not (ROOT / "docs" / f).is_file()]
    assert not missing, f"pages in the nav of mkdocs.yml but not in docs/: {missing}"
    out = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=600,
                       env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1",
                            "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-4000:]
    return out


class _Links(HTMLParser):
    """The ids of a page and the links it holds (href, src)."""

    def __init__(self):
        super().__init__()
        self.ids, self.links = set(), []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name == "id" and value:
                self.ids.add(value)
            if name in ("href", "src") and value is not None:
                self.links.append(value)


def _parse(page: Path) -> _Links:
    p = _Links()
    p.feed(page.read_text(errors="replace"))
    return p


def _target(site: Path, page: Path, url: str) -> tuple[Path, str] | None:
    """The file and fragment an internal link of ``page`` points at (None: external)."""
    parts = urlsplit(url)
    if parts.scheme or parts.netloc or url.startswith(("mailto:", "data:", "javascript:")):
        return None
    path = unquote(parts.path)
    target = page if not path else (
        site / path.lstrip("/") if path.startswith("/") else page.parent / path)
    target = target.resolve()
    if target.is_dir():
        target = target / "index.html"
    return target, unquote(parts.fragment)


def test_site_builds_strict_and_every_internal_link_resolves(site):
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 20
    parsed = {p.resolve(): _parse(p) for p in pages}
    broken = []
    for page, links in parsed.items():
        for url in links.links:
            found = _target(site, page, url)
            if found is None:
                continue
            target, fragment = found
            if not target.is_file():
                broken.append(f"{page.relative_to(site)}: {url} (no such file)")
            elif fragment and target.suffix == ".html" and fragment not in (
                    parsed.get(target) or _parse(target)).ids:
                broken.append(f"{page.relative_to(site)}: {url} (no such anchor)")
    assert not broken, "\n".join(broken)


def _text(page: Path) -> str:
    import html

    return html.unescape(re.sub(r"<[^>]+>", " ", page.read_text()))


def test_reference_holds_every_flag_command_route_and_field(site):
    """Enumerated from the code here, looked up in the built pages."""
    from oga.cli import build_parser

    import html

    page = (site / "reference" / "cli" / "index.html").read_text()
    parts = re.split(r'<h2 id="(oga-[\w-]+)"', page)  # each command's section by its anchor
    sections = {k: html.unescape(re.sub(r"<[^>]+>", " ", v))
                for k, v in zip(parts[1::2], parts[2::2])}
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    missing = []
    for name, parser in sub.choices.items():
        section = sections.get(f"oga-{name}")
        if section is None:
            missing.append(f"oga {name}")
            continue
        for action in parser._actions:
            for flag in action.option_strings or [action.metavar or action.dest]:
                if f"{flag} " not in section:
                    missing.append(f"oga {name} {flag}")
    assert not missing, f"CLI reference lacks {missing}"

    from fastapi.routing import APIRoute

    from api import routes as api_routes
    from api.app import Settings, create_app

    app = create_app(Settings(db_path=str(site / "unused.db"), workers=0))
    rest = _text(site / "reference" / "rest" / "index.html")
    routes = [(m, r.path) for r in [*api_routes.router.routes, *app.routes]
              if isinstance(r, APIRoute) and r.include_in_schema for m in sorted(r.methods)]
    assert len(routes) >= 13
    missing = [f"{m} {p}" for m, p in routes if f"{m} {p}" not in " ".join(rest.split())]
    assert not missing, f"REST reference lacks {missing}"

    from oga.defaults import MACHINE_FIELD_RANGES
    from oga.model.machine import Machine

    ref = _module(ROOT / "docs" / "hooks" / "reference.py")
    machine = _text(site / "reference" / "machine-file" / "index.html")
    paths = []

    def walk(model, prefix):
        for name, info in model.model_fields.items():
            paths.append(prefix + name)
            inner = info.annotation
            if typing.get_origin(inner) is dict:
                inner, name = typing.get_args(inner)[1], name + ".<a>"
            for t in (inner, *typing.get_args(inner)):
                if isinstance(t, type) and hasattr(t, "model_fields"):
                    walk(t, f"{prefix}{name}.")

    walk(Machine, "")
    assert "axes.<a>.cascade.mass_kg" in paths and "planner.jerk_fraction" in paths
    missing = [p for p in paths if p not in machine] + [
        k for k in MACHINE_FIELD_RANGES if k not in machine]
    assert not missing, f"machine-file reference lacks {missing}"
    stale = sorted(set(ref.FIELD_NOTES) - set(paths))
    assert not stale, f"FIELD_NOTES of docs/hooks/reference.py name no field: {stale}"

    python = _text(site / "reference" / "python" / "index.html")
    import oga

    missing = [n for n in oga._EXPORTS if n not in python]
    assert not missing, f"Python API reference lacks {missing}"


def _runnable_pages() -> list[Path]:
    return [p for p in runnable.pages() if runnable.blocks(p)]


@pytest.mark.parametrize("page", _runnable_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_runnable_blocks_print_what_the_page_shows(page):
    problems = runnable.check([page])
    assert not problems, ("\n".join(problems) + "\n(after a change of the code: python "
                          "docs/scripts/runnable.py --update " + str(page.relative_to(ROOT)) + ")")


def test_readme_is_short_with_the_figure_and_two_quickstart_commands():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 200
    block = readme.split("## Quickstart", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    install, tests = block.strip().splitlines()  # exactly two command lines
    assert tests in (ROOT / ".ci" / "run").read_text().splitlines()
    # the output shown is that of the Quickstart's oga command (checked by the runnable test)
    shown = runnable.blocks(ROOT / "README.md")[0].commands[0]
    assert install.endswith("&& " + shown) and "oga optimize" in shown
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", readme)
    assert figures and all((ROOT / f).is_file() for f in figures)
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", readme)
    broken = [u for u in links if not urlsplit(u).scheme and not (ROOT / u).exists()]
    assert not broken, f"README links to files that do not exist: {broken}"
    # a table for one's own machine: one click from the README
    assert "(docs/tutorials/your-machine.md)" in readme


def test_runnable_comparison_catches_a_changed_figure_and_ignores_layout():
    """The comparison the runnable test relies on, on lines it must pass and fail."""
    same = "  MSE ratio to the fixed baseline: median 0.132, p90 0.231, worst 0.421"
    assert not runnable.line_differs(same, same.replace("  ", "   "), 0.01, None)
    assert not runnable.line_differs(same, same.replace("0.231", "0.232"), 0.0, None)
    assert runnable.line_differs(same, same.replace("0.231", "0.240"), 0.01, None)
    assert runnable.line_differs(same, same.replace("worst", "best"), 0.01, None)
    assert runnable.line_differs("x 1.3 s", "x 2.5 s", 0.01, None)
    assert not runnable.line_differs("x 1.3 s", "x 2.5 s", 0.01, r"[\d.]+ s")
    assert not runnable.line_differs("1e-05", "0.00001", 0.0, None)


def test_figure_script_draws_with_names_the_report_code_has():
    """``docs/scripts/figures.py`` draws with the report's own functions: each name it imports
    exists (drawing the figures takes a minute and a browser: the script, not the suite)."""
    import ast
    import importlib

    tree = ast.parse((ROOT / "docs" / "scripts" / "figures.py").read_text())
    imports = [(n.module, a.name) for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
               and n.module and n.module.split(".")[0] in ("oga", "feedplan") for a in n.names]
    assert ("oga.report.optimize", "_fig_ratio") in imports
    missing = [f"{m}.{a}" for m, a in imports if not hasattr(importlib.import_module(m), a)]
    assert not missing, f"docs/scripts/figures.py imports names that no longer exist: {missing}"

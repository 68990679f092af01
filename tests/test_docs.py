"""The documentation: the site builds strictly with every package, public name and
benchmark result on it, every public name has a docstring, and the README is a front page.

The strict build (``mkdocs build --strict``) fails on a broken link or anchor, a missing
page, a docstring mkdocstrings cannot render and a generated part the hook cannot make
(``docs/hooks/generate.py``), so the docs cannot rot. It needs the docs tools
(``pip install -e ".[docs]"``; skipped without them) and no network. The generated parts
committed in the pages (docs/cli.md) are checked against the code without those tools;
every page's examples run in tests/test_docs_examples.py.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
from html import unescape

import pytest
from helpers import REPO

import jaxbvh

DOCS = REPO / "docs"
README = REPO / "README.md"


def public_modules() -> list[str]:
    """Every module of the package with no ``_`` part, twins included."""
    names = ["jaxbvh"]
    for info in pkgutil.walk_packages(jaxbvh.__path__, "jaxbvh."):
        if not any(part.startswith("_") for part in info.name.split(".")):
            names.append(info.name)
    return names


def public_names(module) -> list[tuple[str, object]]:
    """``(qualified name, object)`` of a module's public functions and classes (its
    ``__all__``, else those defined in it) and of their public methods."""
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n, v in vars(module).items() if not n.startswith("_")
                 and (inspect.isfunction(v) or inspect.isclass(v)) and v.__module__ == module.__name__]
    out = []
    for name in names:
        value = getattr(module, name)
        if not (inspect.isfunction(value) or inspect.isclass(value)):
            continue
        out.append((f"{module.__name__}.{name}", value))
        if inspect.isclass(value):
            out += [(f"{module.__name__}.{name}.{m}", f) for m, f in vars(value).items()
                    if not m.startswith("_") and inspect.isfunction(f)]
    return out


def test_every_public_name_has_a_docstring():
    """Every public module, function, class and method says what it is (the API pages are
    made from these)."""
    missing = []
    for name in public_modules():
        module = importlib.import_module(name)
        if not (module.__doc__ or "").strip():
            missing.append(f"{name} (module)")
        for qualified, value in public_names(module):
            # a class's own __doc__ (dataclasses make one from the signature when it has none)
            doc = value.__doc__ if inspect.isfunction(value) else vars(value).get("__doc__")
            if not (doc or "").strip() or (inspect.isclass(value) and doc.startswith(f"{value.__name__}(")):
                missing.append(qualified)
    assert not missing, "public names without a docstring:\n" + "\n".join(sorted(set(missing)))


def test_readme_is_a_front_page():
    """README: at most ~150 lines, the two set-up commands CI runs, links that resolve."""
    text = README.read_text()
    assert len(text.splitlines()) <= 150, "README is a front page: move detail into docs/"
    assert 'pip install -e ".[test]" && jaxbvh build' in text and "python -m pytest -q" in text
    broken = [link for link in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text)
              if "://" not in link and not (REPO / link).exists()]
    assert not broken, f"README links to missing files: {broken}"


def test_site_builds_strictly(tmp_path):
    """``mkdocs build --strict``: no warning (broken links and anchors, docstrings that do
    not render, unknown generated parts); every nav page and the API pages come out."""
    pytest.importorskip("mkdocs", reason="the docs tools are not installed (pip install -e '.[docs]')")
    for plugin in ("material", "mkdocstrings_handlers.python", "mkdocs_jupyter"):
        pytest.importorskip(plugin, reason=f"{plugin} is not installed (pip install -e '.[docs]')")
    site = tmp_path / "site"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               NO_MKDOCS_2_WARNING="1")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-f", str(REPO / "mkdocs.yml"),
                          "-d", str(site)], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f"mkdocs build --strict failed:\n{run.stdout}\n{run.stderr}"
    for page in ("index.html", "getting-started/index.html", "builders/index.html", "cli/index.html",
                 "api/tree/index.html", "notebooks/builders/index.html", "bench/optimize.png"):
        assert (site / page).is_file(), f"{page} missing from the built site"
    html = "\n".join(p.read_text() for p in site.rglob("*.html"))
    assert "&lt;!-- gen:" not in html and "<!-- gen:" not in html, "a generated part was left unexpanded"
    api = "\n".join(p.read_text() for p in (site / "api").rglob("*.html"))
    absent = [name for name in jaxbvh.__all__ if 'id="jaxbvh.' not in api or name not in api]
    assert not absent, f"public names missing from the API pages: {absent}"
    packages = [i.name for i in pkgutil.iter_modules(jaxbvh.__path__) if i.ispkg and not i.name.startswith("_")]
    absent = [name for name in packages if not (site / "api" / name / "index.html").is_file()]
    assert not absent, f"packages without an API page: {absent}"
    # every benchmark table and plot is on the site (docs/benchmarks.md's "Other results"
    # takes any that no page shows): the file's title, the plot's file and a link to it
    results = REPO / "bench" / "results"
    text = " ".join(unescape(re.sub(r"<[^>]+>", "", html)).split())
    for table in sorted(results.glob("*.md")):
        title = next(line for line in table.read_text().splitlines() if line.startswith("#")).lstrip("# ")
        assert " ".join(title.replace("`", "").split()) in text, f"bench/results/{table.name} is on no page"
    for plot in sorted(results.glob("*.png")):
        assert (site / "bench" / plot.name).is_file() and f"bench/{plot.name}" in html, f"{plot.name} is on no page"


def docs_hook():
    """docs/hooks/generate.py, the site's hook, as a module (it needs no docs tools)."""
    spec = importlib.util.spec_from_file_location("docs_generate", DOCS / "hooks" / "generate.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    return hook


def test_committed_generated_parts_are_current():
    """Every part committed between ``<!-- gen: ... -->`` and ``<!-- end gen -->`` (the
    command-line reference's synopsis and ``--help`` texts) is what the code gives now:
    ``python docs/hooks/generate.py`` rewrites them."""
    hook = docs_hook()
    stale = [str(page.relative_to(REPO)) for page in sorted(DOCS.rglob("*.md"))
             if hook.BLOCK.search(page.read_text()) and hook.refresh(page.read_text()) != page.read_text()]
    assert not stale, f"generated parts out of date in {stale}: run python docs/hooks/generate.py {' '.join(stale)}"


def test_cli_reference_reads_whole_as_a_file():
    """docs/cli.md holds its generated text (no marker left for the build to fill), a
    ``--help`` section for every command, ``batch`` included, and every exit status the
    command line returns in its table."""
    from jaxbvh.cli import app, command_names, front

    hook = docs_hook()
    page = (DOCS / "cli.md").read_text()
    unfilled = [m.group(0) for m in hook.MARK.finditer(hook.BLOCK.sub("", page))]
    assert not unfilled, f"docs/cli.md has parts only the site build fills: {unfilled}"
    helps = {m.group("args").strip() for m in hook.BLOCK.finditer(page) if m.group("kind") == "help"}
    assert set(command_names()) <= helps, f"commands without their --help in docs/cli.md: {set(command_names()) - helps}"
    assert "batch" in helps
    table = page[page.index("## Exit status"):]
    table = table[:table.index("\n\n", table.index("| status"))]
    listed = {int(code) for code in re.findall(r"^\| (\d+) \|", table, flags=re.M)}
    codes = {0, front.EXIT_USAGE, app.EXIT_INVALID, app.EXIT_INTERRUPTED}
    assert listed == codes, f"exit statuses in docs/cli.md {sorted(listed)}, the command line's {sorted(codes)}"


def readme_python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), flags=re.S)


def test_readme_example_optimizes_and_exits(tmp_path):
    """The example's optimize line makes passes (its budget counts the search, not the
    compiling), it saves its tree, and the interpreter exits when its last line is done
    (no compile left running in the background)."""
    blocks = readme_python_blocks()
    assert len(blocks) == 1
    script = tmp_path / "readme_example.py"
    script.write_text(blocks[0] + "\nimport time\nprint('LAST', time.time(), flush=True)\n")
    import time

    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    ended = time.time()
    assert done.returncode == 0, done.stderr[-3000:]
    passes = re.search(r"^(\d+) passes: SAH ([\d.]+)", done.stdout, flags=re.M)
    assert passes and int(passes.group(1)) >= 1, done.stdout
    sah_line = re.search(r"^SAH ([\d.]+)", done.stdout, flags=re.M)
    assert float(passes.group(2)) < float(sah_line.group(1))  # the optimizer improved the tree
    assert (tmp_path / "spot.npz").exists()
    last = float(re.search(r"^LAST ([\d.]+)", done.stdout, flags=re.M).group(1))
    assert ended - last < 30  # generous on a loaded machine; bench/bench_compile.py times it
    assert "warning" not in done.stderr.lower(), done.stderr

"""The guides are a manual, not a lab notebook: measured figures live on the results pages.

Issue 37: "No guide page carries more than about 10 measured figures; the figures live in the
results pages." A *guide* is a page of the ``Guides`` toctree of ``docs/index.md``. A *figure*
is, in the page's text outside fenced code blocks, inline code spans and MyST directive options:

- a number with a decimal point (``0.97``, ``.076``, ``1.5``), or
- a number followed by ``%`` (``5 %``, ``12%``) or by one of the units a measurement is quoted
  in (``dB``, ``lx``, ``cd/m2``/``cd/m²``, ``MB``, ``s``, ``ms``, ``x`` as a ratio ``1.8x``).

Every such number counts once, in prose and in table cells alike, so one table row of five
ratios counts five. Section numbers (``Sec. 2.1``, ``eq. 11``), versions (``HDRutils 1.2``,
``OpenCV 4.14``), f-numbers (``f/5.6``) and Rec. 709 style names are not figures. Formulas and
option values belong in inline code (where they are typed), and are not counted.

The results pages say, for every table, whose data it holds (tuning, held out, real), and every
``derender`` command in a page's shell blocks names a command and options the CLI has.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"

#: The most figures a guide page may carry (issue 37: "about 10").
LIMIT = 10

_FENCE = re.compile(r"^(```|~~~|:::)")
_NOT_A_FIGURE = re.compile(
    r"(?:\b(?:Sec|Section|eq|Eq|Eqs|Fig|Table|Alg|version|v|Rec|ITU-R BT|HDRutils|OpenCV|numpy|"
    r"Python|Pillow|Chromium|rawpy|colour-science|Radiance|LibRaw)\.?\s+|f/|\bv)$")
_FIGURE = re.compile(
    r"(?<![\w./-])(?P<num>\d*\.\d+|\d+)(?P<unit>\s?(?:%|dB\b|lx\b|cd/m2|cd/m²|MB\b|ms\b|s\b|x\b))?")


def guide_pages() -> list[str]:
    """The pages of ``docs/index.md``'s ``Guides`` toctree, in order."""
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    assert ":caption: Guides" in index, "docs/index.md has no 'Guides' toctree"
    body = index.split(":caption: Guides", 1)[1].split("```", 1)[0]
    return [line.strip() for line in body.splitlines() if line.strip() and not line.startswith(":")]


def prose(text: str) -> str:
    """The page's text without fenced blocks (code, directives), inline code, links' targets,
    HTML comments and MyST roles' targets."""
    out, fence = [], None
    for line in text.splitlines():
        m = _FENCE.match(line.lstrip())
        if fence is None and m:
            fence = line.lstrip()[:3]
            continue
        if fence is not None:
            if line.lstrip().startswith(fence) and line.strip().strip("`~:") == "":
                fence = None
            continue
        out.append(line)
    text = "\n".join(out)
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    text = re.sub(r"`[^`]*`", " ", text)                       # inline code and role targets
    text = re.sub(r"\]\([^)]*\)", "]", text)                   # link targets
    return text


def measured_figures(text: str) -> list[str]:
    """Every figure (see the module docstring) in a page's text, in order."""
    found = []
    body = prose(text)
    for m in _FIGURE.finditer(body):
        num, unit = m.group("num"), (m.group("unit") or "").strip()
        before = body[max(0, m.start() - 24):m.start()]
        if _NOT_A_FIGURE.search(before):
            continue
        if "." in num or unit:
            found.append(num + (" " + unit if unit else ""))
    return found


def test_the_counter_counts():
    """The definition on a known sample: prose, a table row, and what is not a figure."""
    sample = "\n".join([
        "The merge is 1.5x faster and within 5 % (p95 .076); 42.90 dB, 839.634 lx.",
        "| paper (tuning) | 0.98 | 1.13 |",
        "See Sec. 2.1, eq. 11, HDRutils 1.2, f/5.6, `--spot 812,604,40,40=212`, `q = 0.65`.",
        "```bash", "derender merge a/ --option lambda=0.5   # 3.5 s", "```",
        "Shoot 3 to 9 exposures 1 to 2 stops apart.",
    ])
    assert measured_figures(sample) == ["1.5 x", "5 %", ".076", "42.90 dB", "839.634 lx", "0.98", "1.13"]


def test_guides_are_the_index_toctree():
    pages = guide_pages()
    assert pages[:2] == ["getting-started", "which-method"], pages      # the docs open with getting started
    assert all((DOCS / f"{p}.md").is_file() for p in pages), pages


@pytest.mark.parametrize("page", guide_pages())
def test_guide_page_keeps_its_figures_on_the_results_pages(page):
    figures = measured_figures((DOCS / f"{page}.md").read_text(encoding="utf-8"))
    assert len(figures) <= LIMIT, (
        f"docs/{page}.md carries {len(figures)} measured figures (limit {LIMIT}); move them to its "
        f"results page and link to it: {figures}")


_ROLE = re.compile(r"tuning|held out|held-out|real bracket|judge|no tuning|no family|exact check", re.I)


def _tables_without_a_role(text: str) -> list[str]:
    """The first row of every table whose own cells, the heading it sits under and the
    paragraph before it do not say whose data it holds (tuning, held out, real)."""
    lines = prose(text).splitlines()
    bad, heading, i = [], "", 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            heading = line
        if line.lstrip().startswith("|"):
            j = i
            while j < len(lines) and lines[j].lstrip().startswith("|"):
                j += 1
            k = i - 1
            while k >= 0 and not lines[k].strip():
                k -= 1
            while k >= 0 and lines[k].strip() and not lines[k].startswith("#"):
                k -= 1
            context = "\n".join([heading, *lines[k + 1:j]])
            if not _ROLE.search(context):
                bad.append(line.strip()[:80])
            i = j
            continue
        i += 1
    return bad


#: The results pages: the ``Results`` toctree of ``docs/index.md``.
RESULTS = sorted(set(p.stem for p in DOCS.glob("results-*.md")) | {"results", "paper1", "paper2", "uncertainty"})


@pytest.mark.parametrize("page", RESULTS)
def test_every_results_table_says_whose_data_it_holds(page):
    bad = _tables_without_a_role((DOCS / f"{page}.md").read_text(encoding="utf-8"))
    assert not bad, f"docs/{page}.md: tables that do not say tuning, held out or real: {bad}"


def test_results_pages_are_in_the_results_toctree():
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    results = index.split(":caption: Results", 1)[1].split("```", 1)[0]
    assert all(p in results.split() for p in RESULTS), RESULTS


def _documented_commands(text: str) -> list[list[str]]:
    """The ``derender ...`` command lines of a page's ``bash`` blocks, split as the shell would
    (continuation lines joined, comments dropped)."""
    import shlex

    out = []
    for block in re.findall(r"```(?:bash|console|sh)\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip()
            if not line.startswith("derender "):
                continue
            line = re.sub(r"\$\([^)]*\)", "X", line)               # $(...) substitutions
            words = shlex.split(line, comments=True)
            for sep in ("&&", "|", ";"):
                if sep in words:
                    words = words[:words.index(sep)]
            out.append(words[1:])
    return out


@pytest.mark.parametrize("page", sorted(p.stem for p in DOCS.glob("*.md")))
def test_documented_commands_and_options_exist(page):
    """Every ``derender`` command in a page's shell blocks names a command and options the CLI
    has (a renamed or removed command or option fails here, not in a reader's terminal)."""
    import typer

    from derender.cli import app

    root = typer.main.get_command(app)
    bad = []
    for words in _documented_commands((DOCS / f"{page}.md").read_text(encoding="utf-8")):
        cmd, rest = root, list(words)
        while hasattr(cmd, "commands") and rest and rest[0] in cmd.commands:     # typer vendors click
            cmd = cmd.commands[rest.pop(0)]
        if hasattr(cmd, "commands"):
            bad.append(f"derender {' '.join(words)}: no such command")
            continue
        options = {o: p for p in cmd.params for o in (*p.opts, *p.secondary_opts) if o.startswith("-")}
        skip = False
        for w in rest:
            if skip:                                                   # an option's value (may start with -)
                skip = False
                continue
            name = w.split("=", 1)[0]
            if not w.startswith("-") or re.fullmatch(r"-?\d[\d.,]*", w) or name == "--help":
                continue
            if name not in options:
                bad.append(f"derender {' '.join(words)}: {cmd.name} has no option {name}")
            elif "=" not in w and not getattr(options[name], "is_flag", False):
                skip = True
    assert not bad, "\n".join(bad)

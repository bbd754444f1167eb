"""The README and docs/ stay true: links resolve inside the repository, every command in a command
block names something that exists, and the README's results come from committed files."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parent.parent
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
BLOCK = re.compile(r"```(?:bash|sh|console)\n(.*?)```", re.S)
# Tools a reader brings or the system has; everything else must be ours (a make target, a script,
# a console script of pyproject.toml, a file or module in this repository).
EXTERNAL = {"helm", "kubectl", "docker", "git", "curl", "nvidia-smi", "tar", "cp", "rm", "ls", "cd", "export",
            "python", "python3", "pip", "sudo", "apt-get", "echo", "cat", "TRITON_INTERPRET=1"}
VENV_TOOLS = {"python", "pytest", "ruff", "dagster", "pip"}


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    return {_slug(m) for m in re.findall(r"^#+ (.+)$", page.read_text(), re.M)}


def _links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # code is not a link
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+://|mailto:", t)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_resolves_inside_the_repository(page: Path) -> None:
    for target in _links(page):
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        assert resolved.is_relative_to(REPO), f"{page.name}: {target} points outside the repository"
        assert resolved.exists(), f"{page.name}: {target} does not exist"
        if anchor and resolved.suffix == ".md":
            assert anchor in _anchors(resolved), f"{page.name}: no heading #{anchor} in {resolved.name}"


def _commands(page: Path) -> list[list[str]]:
    out = []
    for block in BLOCK.findall(page.read_text()):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #")[0].strip()
            if not line or line.startswith("#"):
                continue
            words = shlex.split(line)
            while words and re.match(r"^[A-Z_][A-Z0-9_]*=", words[0]):  # VAR=value before the command
                words = words[1:]
            if words:
                out.append(words)
    return out


def _targets() -> set[str]:
    return set(re.findall(r"^([a-z][\w-]*):", (REPO / "Makefile").read_text(), re.M))


def _scripts() -> set[str]:
    return set(tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"])


def _module_exists(name: str) -> bool:
    base = REPO / Path(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _problem(words: list[str]) -> str | None:
    exe, rest = words[0], words[1:]
    if exe == "make":
        missing = [t for t in rest if "=" not in t and not t.startswith("-") and t not in _targets()]
        return f"no Makefile target {missing}" if missing else None
    if exe == "bash" and rest:
        return None if (REPO / rest[0]).is_file() else f"no script {rest[0]}"
    name = exe.removeprefix(".venv/bin/")
    if name in ("python", "python3") and rest:
        if rest[0] == "-m":
            return None if _module_exists(rest[1]) or rest[1] in ("pip", "pytest") else f"no module {rest[1]}"
        if rest[0].endswith(".py"):
            return None if (REPO / rest[0]).is_file() else f"no file {rest[0]}"
    if exe.startswith(".venv/bin/"):
        return None if name in _scripts() | VENV_TOOLS else f"no console script {name} in pyproject.toml"
    return None if exe in EXTERNAL else f"unknown executable {exe!r} (ours, or add it to EXTERNAL)"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_command_names_something_that_exists(page: Path) -> None:
    problems = [f"{' '.join(w)}: {p}" for w in _commands(page) if (p := _problem(w))]
    assert not problems, f"{page.name}:\n" + "\n".join(problems)


def test_the_checks_catch_what_they_are_for(tmp_path: Path) -> None:
    """A broken link, a missing target, a missing module and an unknown tool are all reported."""
    assert _problem(["make", "no-such-target"]) and _problem([".venv/bin/python", "-m", "benchmarks.nope"])
    assert _problem(["frobnicate", "--now"]) and _problem([".venv/bin/morpheus4d"])
    assert _problem(["make", "demo"]) is None and _problem([".venv/bin/morpheus3d", "run"]) is None
    page = tmp_path / "p.md"
    page.write_text("see [x](nowhere.md) and [y](https://example.com)\n```bash\nmake demo\n```\n")
    assert _links(page) == ["nowhere.md"] and _commands(page) == [["make", "demo"]]


def test_readme_is_a_users_page() -> None:
    lines = (REPO / "README.md").read_text().splitlines()
    assert 100 <= len(lines) <= 250, f"README.md has {len(lines)} lines: keep it to what users need, rest in docs/"
    assert "../shared" not in "\n".join(lines), "the README links outside the repository"


def test_readme_results_come_from_the_linked_files() -> None:
    """Every decimal number in a README table row that links a committed result file appears in that file."""
    rows = [line for line in (REPO / "README.md").read_text().splitlines()
            if line.startswith("|") and re.search(r"\(benchmarks/results/[^)]+\.md\)", line)]
    assert rows, "the README has a results table linking benchmarks/results/"
    for row in rows:
        files = [REPO / t for t in LINK.findall(row) if t.startswith("benchmarks/results/") and t.endswith(".md")]
        text = "".join(f.read_text() for f in files)
        for number in re.findall(r"(?<![\w.])\d+\.\d+(?![\w.])", row):
            assert number in text, f"README: {number} is in none of {[f.name for f in files]}"

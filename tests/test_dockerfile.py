"""The user-code image (``Dockerfile``, ``.dockerignore``), checked offline against the files it must
agree with: the Makefile's set-up, pyproject's Python range, the Helm values' code location and port.

Only ``test_docker_build`` needs a Docker engine; it runs when one answers and MORPHEUS_TEST_DOCKER=1.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import posixpath
import re
import secrets
import shlex
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from packaging.specifiers import SpecifierSet

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = REPO / "Dockerfile"
DOCKERIGNORE = REPO / ".dockerignore"
MAKEFILE = REPO / "Makefile"
PYPROJECT = REPO / "pyproject.toml"
VALUES_YAML = REPO / "deploy" / "k8s" / "values.yaml"
DOCKER_ENV = "MORPHEUS_TEST_DOCKER"
OWN_PIP = re.compile(r"\bpip3?\s+install\b|-m\s+pip\b|\buv\s+pip\b|\bconda\s+install\b|\bpoetry\s+install\b")


# --- parsing ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Instruction:
    keyword: str
    args: str

    def flags_and_rest(self) -> tuple[list[str], str]:
        """Leading ``--flag=...`` options (RUN --mount, COPY --chown) and the rest of the arguments."""
        flags, rest = [], self.args
        while rest.startswith("--"):
            flag, _, rest = rest.partition(" ")
            flags.append(flag)
            rest = rest.lstrip()
        return flags, rest

    def argv(self) -> list[str]:
        """The exec form as its JSON list; the shell form as the ``/bin/sh -c`` Docker runs."""
        rest = self.flags_and_rest()[1]
        if rest.startswith("["):
            argv = json.loads(rest)
            assert isinstance(argv, list) and all(isinstance(a, str) for a in argv), rest
            return argv
        return ["/bin/sh", "-c", rest]


def parse_dockerfile(text: str) -> list[Instruction]:
    """Instructions in order: comments, parser directives and blank lines dropped, ``\\`` continuations
    joined (comment and blank lines inside a continuation are dropped, as Docker does)."""
    instructions: list[Instruction] = []
    current = ""
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            current += line[:-1].rstrip() + " "
            continue
        current += line
        keyword, _, args = re.sub(r"\s+", " ", current, count=1).partition(" ")
        if not re.fullmatch(r"[A-Za-z]+", keyword):
            raise ValueError(f"Dockerfile line {number}: {keyword!r} is not an instruction")
        instructions.append(Instruction(keyword.upper(), args.strip()))
        current = ""
    if current:
        raise ValueError("Dockerfile ends inside a line continuation")
    return instructions


def env_of(instructions: list[Instruction]) -> dict[str, str]:
    """The image's ENV (``KEY=VALUE ...`` and the old ``KEY VALUE`` form), ``$VAR`` left unexpanded."""
    env: dict[str, str] = {}
    for ins in instructions:
        if ins.keyword != "ENV":
            continue
        tokens = shlex.split(ins.args, posix=True)
        if tokens and "=" not in tokens[0]:
            env[tokens[0]] = " ".join(tokens[1:])
            continue
        for token in tokens:
            key, sep, value = token.partition("=")
            assert sep, f"ENV {ins.args!r}: {token!r} has no '='"
            env[key] = value
    return env


def copy_sources(ins: Instruction) -> list[str]:
    flags, rest = ins.flags_and_rest()
    assert not any(f.startswith("--from") for f in flags), "a multi-stage COPY --from is not expected"
    tokens = json.loads(rest) if rest.startswith("[") else shlex.split(rest)
    assert len(tokens) >= 2, ins.args
    return [t.rstrip("/") or "." for t in tokens[:-1]]


def _glob_regex(pattern: str) -> str:
    """A .dockerignore pattern (Go filepath.Match plus ``**``) as a regular expression."""
    out, i = [], 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
        elif pattern.startswith("**", i):
            out.append(".*")
            i += 2
        elif pattern[i] == "*":
            out.append("[^/]*")
            i += 1
        elif pattern[i] == "?":
            out.append("[^/]")
            i += 1
        elif pattern[i] == "[":
            end = pattern.index("]", i + 1)
            body = pattern[i + 1 : end]
            out.append("[" + ("^" + body[1:] if body.startswith("^") else body).replace("\\", "\\\\") + "]")
            i = end + 1
        else:
            out.append(re.escape(pattern[i]))
            i += 1
    return "".join(out)


def dockerignore_rules(text: str) -> list[tuple[bool, re.Pattern[str]]]:
    """(is an exception ``!``, regex) per pattern; a pattern also matches everything below what it matches."""
    rules = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = posixpath.normpath(line.removeprefix("!").strip().strip("/"))
        rules.append((negate, re.compile(_glob_regex(pattern) + "(?:/.*)?")))
    return rules


def is_ignored(path: str, rules: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether Docker leaves ``path`` (relative to the context) out: the last matching rule decides."""
    ignored = False
    for negate, regex in rules:
        if regex.fullmatch(path):
            ignored = not negate
    return ignored


def makefile_vars_and_rules(text: str) -> tuple[dict[str, str], dict[str, tuple[list[str], list[str]]]]:
    """``VAR := value`` / ``VAR ?= value`` assignments and ``target: prerequisites`` with their recipe lines."""
    variables: dict[str, str] = {}
    rules: dict[str, tuple[list[str], list[str]]] = {}
    current: str | None = None
    for line in text.replace("\\\n", " ").splitlines():
        if line.startswith("\t") and current is not None:
            rules[current][1].append(line.strip())
            continue
        current = None
        if m := re.match(r"^([A-Z_]+)\s*[:?]?=\s*(.*)$", line):
            variables[m[1]] = m[2].strip()
        elif (m := re.match(r"^([^\s:#=][^:=]*):(?!=)\s*(.*)$", line)) and not line.startswith("."):
            current = m[1].strip()
            rules[current] = (m[2].split(), [])
    return variables, rules


@pytest.fixture(scope="module")
def dockerfile() -> list[Instruction]:
    return parse_dockerfile(DOCKERFILE.read_text())


@pytest.fixture(scope="module")
def pyproject() -> dict:
    return tomllib.loads(PYPROJECT.read_text())


@pytest.fixture(scope="module")
def user_deployment() -> dict:
    (deployment,) = yaml.safe_load(VALUES_YAML.read_text())["dagster-user-deployments"]["deployments"]
    return deployment


def workdir(instructions: list[Instruction]) -> str:
    dirs = [ins.args for ins in instructions if ins.keyword == "WORKDIR"]
    assert len(dirs) == 1 and dirs[0].startswith("/"), dirs
    return dirs[0]


def install_packages(pyproject: dict) -> list[str]:
    """The top-level package folders pyproject's package discovery includes."""
    return sorted(p.rstrip("*").rstrip(".") for p in pyproject["tool"]["setuptools"]["packages"]["find"]["include"])


# --- the parsers themselves -------------------------------------------------------------------


def test_parser_joins_continuations_and_drops_comments() -> None:
    text = "# syntax=docker/dockerfile:1\nFROM python:3.11-slim\nRUN a \\\n  # inside\n && b\nCMD [\"x\", \"y\"]\n"
    parsed = parse_dockerfile(text)
    assert parsed == [Instruction("FROM", "python:3.11-slim"), Instruction("RUN", "a && b"),
                      Instruction("CMD", '["x", "y"]')]
    assert parsed[2].argv() == ["x", "y"]
    assert Instruction("RUN", "--mount=type=cache,target=/c make install").argv() == ["/bin/sh", "-c", "make install"]
    with pytest.raises(ValueError, match="continuation"):
        parse_dockerfile("RUN a \\\n")


def test_dockerignore_matcher() -> None:
    rules = dockerignore_rules(".venv\n**/__pycache__\n*.egg-info\ndata/*\n!data/keep.yaml\n")
    assert is_ignored(".venv", rules) and is_ignored(".venv/bin/python", rules)
    assert is_ignored("ops/engine/__pycache__/loop.cpython-311.pyc", rules)
    assert is_ignored("morpheus3d_batch.egg-info/PKG-INFO", rules)
    assert is_ignored("data/state.db", rules) and not is_ignored("data/keep.yaml", rules)
    assert not is_ignored("ops/engine/loop.py", rules) and not is_ignored("venv", rules)


# --- the install step -------------------------------------------------------------------------


def test_install_step_is_the_makefile_install_target(dockerfile: list[Instruction]) -> None:
    """The image is set up the README's way: `make install`, the target `make demo`/`make test` depend on."""
    runs = [" ".join(ins.argv()[2:]) if ins.argv()[:2] == ["/bin/sh", "-c"] else " ".join(ins.argv())
            for ins in dockerfile if ins.keyword == "RUN"]
    installs = [cmd for cmd in runs if re.search(r"(?:^|&&|;)\s*make(?:\s+-\S+)*\s+install\s*(?:$|&&|;)", cmd)]
    assert len(installs) == 1, f"expected one `make install` RUN, got {installs}"
    own = [cmd for cmd in runs if OWN_PIP.search(cmd)]
    assert not own, f"the Dockerfile installs Python packages itself instead of through the Makefile: {own}"

    variables, rules = makefile_vars_and_rules(MAKEFILE.read_text())
    assert rules["install"][0] == ["$(STAMP)"]
    for target in ("demo", "test"):  # the README's two commands run exactly this set-up first
        assert "$(STAMP)" in rules[target][0], target
    recipe = " ".join(rules["$(STAMP)"][1])
    assert "pip install -q $(TORCH_PIN)" in recipe and '-e ".[dev]"' in recipe
    assert recipe.index("$(TORCH_PIN)") < recipe.index('-e ".[dev]"'), "torch is installed first"
    assert variables["TORCH_PIN"] == "torch==2.13.0"
    readme = (REPO / "README.md").read_text()
    assert "make demo" in readme and "make test" in readme


def test_install_sees_what_it_installs(dockerfile: list[Instruction], pyproject: dict) -> None:
    """`make install` runs after the Makefile, pyproject, its readme and every package are copied in."""
    install_at = next(i for i, ins in enumerate(dockerfile) if ins.keyword == "RUN" and "make install" in ins.args)
    copied = {src for ins in dockerfile[:install_at] if ins.keyword == "COPY" for src in copy_sources(ins)}
    needed = {"Makefile", "pyproject.toml", pyproject["project"]["readme"], *install_packages(pyproject)}
    assert needed <= copied, f"copied only after `make install`, or never: {sorted(needed - copied)}"
    assert not any(ins.keyword == "WORKDIR" for ins in dockerfile[install_at:]), "make must run where it was copied"


def test_base_python_satisfies_requires_python(dockerfile: list[Instruction], pyproject: dict) -> None:
    (base,) = [ins.args for ins in dockerfile if ins.keyword == "FROM"]
    m = re.fullmatch(r"(?:docker\.io/(?:library/)?)?python:(\d+\.\d+)(?:\.\d+)?-slim(?:-[a-z]+)?", base)
    assert m, f"base {base!r} is not an official python:<version>-slim image"
    spec = SpecifierSet(pyproject["project"]["requires-python"])
    assert spec.contains(m[1]), f"python {m[1]} of {base} does not satisfy requires-python {spec}"
    target = pyproject["tool"]["ruff"]["target-version"]  # the code must not use anything newer than the base
    assert tuple(map(int, m[1].split("."))) >= (3, int(target.removeprefix("py3")))


def test_venv_bin_comes_first_on_path(dockerfile: list[Instruction]) -> None:
    variables, _ = makefile_vars_and_rules(MAKEFILE.read_text())
    path = env_of(dockerfile)["PATH"].split(":")
    assert path[0] == posixpath.join(workdir(dockerfile), variables["VENV"], "bin"), path
    assert "$PATH" in path or "${PATH}" in path, "the system PATH must stay behind the venv"
    cmd = [ins for ins in dockerfile if ins.keyword in ("CMD", "ENTRYPOINT")]
    assert cmd[-1].argv()[0] == "dagster", "the default command is the venv's dagster, found through PATH"


def test_default_command_serves_the_helm_code_location(dockerfile: list[Instruction], user_deployment: dict) -> None:
    entrypoint = [ins.argv() for ins in dockerfile if ins.keyword == "ENTRYPOINT"]
    cmds = [ins.argv() for ins in dockerfile if ins.keyword == "CMD"]
    assert cmds, "no CMD"
    argv = (entrypoint[-1] if entrypoint else []) + cmds[-1]
    assert argv[:3] == ["dagster", "api", "grpc"], argv

    def option(*names: str) -> str:
        hits = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a in names]
        assert len(hits) == 1, f"{names} in {argv}"
        return hits[0]

    grpc_args = user_deployment["dagsterApiGrpcArgs"]
    module = grpc_args[grpc_args.index("--module-name") + 1]
    assert option("--module-name", "-m") == module, f"values.yaml serves {module}"
    assert int(option("--port", "-p")) == user_deployment["port"], f"values.yaml's port is {user_deployment['port']}"
    assert option("--host", "-h") == "0.0.0.0"  # reachable from the webserver and daemon pods
    exposed = {int(p.split("/")[0]) for ins in dockerfile if ins.keyword == "EXPOSE" for p in ins.args.split()}
    assert user_deployment["port"] in exposed


def test_served_module_is_copied_and_defines_definitions(dockerfile: list[Instruction], user_deployment: dict) -> None:
    from dagster import Definitions

    grpc_args = user_deployment["dagsterApiGrpcArgs"]
    module = grpc_args[grpc_args.index("--module-name") + 1]
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin, f"{module} not found"
    origin = Path(spec.origin).resolve()
    assert origin.is_relative_to(REPO), origin
    copied = {src for ins in dockerfile if ins.keyword == "COPY" for src in copy_sources(ins)}
    assert origin.relative_to(REPO).parts[0] in copied, f"{origin} is not copied into the image"
    defs = importlib.import_module(module).defs
    assert isinstance(defs, Definitions)


# --- .dockerignore ----------------------------------------------------------------------------


def test_dockerignore_excludes_local_state() -> None:
    rules = dockerignore_rules(DOCKERIGNORE.read_text())
    for path in (".venv", ".venv/bin/python", "outputs", "outputs/demo/mug/bake/model.glb", ".git/HEAD",
                 "dagster_home/runs.db", "dagster_home_postgres/storage", "ops/__pycache__/cli.cpython-311.pyc"):
        assert is_ignored(path, rules), f"{path} would be sent into the build context"


def test_dockerignore_keeps_what_the_image_copies(dockerfile: list[Instruction], pyproject: dict) -> None:
    rules = dockerignore_rules(DOCKERIGNORE.read_text())
    copied = {src for ins in dockerfile if ins.keyword == "COPY" for src in copy_sources(ins)}
    needed = {"Makefile", "pyproject.toml", pyproject["project"]["readme"], *install_packages(pyproject)}
    assert {"assets_store", "morpheus_core", "ops", "orchestration"} <= needed
    for src in sorted(needed | copied):
        path = REPO / src
        assert path.exists(), f"{src} is copied but missing"
        assert not is_ignored(src, rules), f".dockerignore excludes {src}"
        if path.is_dir():
            files = [p for p in path.rglob("*") if p.is_file() and "__pycache__" not in p.parts]
            assert files, src
            excluded = [str(p.relative_to(REPO)) for p in files if is_ignored(p.relative_to(REPO).as_posix(), rules)]
            assert not excluded, f".dockerignore excludes files under {src}: {excluded[:5]}"


# --- the real build ---------------------------------------------------------------------------


def _docker_unavailable() -> str | None:
    reasons = []
    if os.environ.get(DOCKER_ENV) != "1":
        reasons.append(f"{DOCKER_ENV}=1 is not set (the build downloads several GB: the CUDA torch wheels)")
    docker = shutil.which("docker")
    if docker is None:
        reasons.append("no docker client on PATH")
    else:
        try:
            info = subprocess.run([docker, "info"], capture_output=True, text=True, timeout=60)
        except subprocess.TimeoutExpired:
            reasons.append("`docker info` did not answer within 60 s")
        else:
            if info.returncode != 0:
                last = (info.stderr.strip().splitlines() or ["no output"])[-1]
                reasons.append(f"no Docker engine answers (`docker info` exit {info.returncode}: {last})")
    return "; ".join(reasons) or None


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_docker_build(dockerfile: list[Instruction]) -> None:
    """Build the image, then check inside it what the offline tests check in the Dockerfile."""
    why = _docker_unavailable()
    if why:
        pytest.skip(f"docker build not run: {why}")
    docker = shutil.which("docker")
    assert docker is not None
    tag = f"morpheus3d-batch:test-{secrets.token_hex(4)}"
    build = subprocess.run([docker, "build", "-t", tag, str(REPO)], capture_output=True, text=True, timeout=7000)
    assert build.returncode == 0, (build.stdout + build.stderr)[-4000:]
    try:
        config = json.loads(subprocess.run([docker, "image", "inspect", tag], capture_output=True, text=True,
                                           check=True).stdout)[0]["Config"]
        cmd = [ins.argv() for ins in dockerfile if ins.keyword == "CMD"][-1]
        assert config["Cmd"] == cmd
        probe = ("import shutil, cv2, torch; from dagster import Definitions; "
                 "import orchestration.k8s_definitions as m; cv2.ximgproc; "
                 "assert isinstance(m.defs, Definitions); print(shutil.which('dagster'), torch.__version__)")
        run = subprocess.run([docker, "run", "--rm", tag, "python", "-c", probe], capture_output=True, text=True,
                             timeout=600)
        assert run.returncode == 0, run.stdout + run.stderr
        variables, _ = makefile_vars_and_rules(MAKEFILE.read_text())
        dagster_path, torch_version = run.stdout.split()[-2:]
        assert dagster_path == posixpath.join(workdir(dockerfile), variables["VENV"], "bin", "dagster")
        assert torch_version.split("+")[0] == variables["TORCH_PIN"].split("==")[1]
    finally:
        subprocess.run([docker, "image", "rm", "-f", tag], capture_output=True, timeout=300)

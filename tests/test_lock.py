"""The lock (``constraints.txt``) and the project's declared dependencies agree.

``pyproject.toml`` keeps honest ranges for people who install the package into their own
environment; ``constraints.txt`` pins the whole environment the README's commands, ``.ci/run`` and
the container image install (made by ``pip-compile`` from the ``[tool.pip-tools]`` options in
``pyproject.toml``). These tests fail when the two drift apart: a dependency added or narrowed in
``pyproject.toml`` without refreshing the lock, an extra the lock does not cover, or an install
that did not use the lock.
"""

from __future__ import annotations

import re
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
LOCK_TEXT = (ROOT / "constraints.txt").read_text()


def locked() -> dict[str, Version]:
    """``name -> version`` for every ``name==version`` line of the lock (comments skipped)."""
    pins = {}
    for line in LOCK_TEXT.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;]+)\s*(;.*)?", line)
        assert m, f"constraints.txt: {line!r} is not a plain 'name==version' pin"
        pins[canonicalize_name(m.group(1))] = Version(m.group(2))
    return pins


def declared() -> list[Requirement]:
    """The runtime dependencies and those of every extra the lock is made for."""
    project = PYPROJECT["project"]
    extras = PYPROJECT["tool"]["pip-tools"]["extra"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in extras:
        reqs += [Requirement(r) for r in project["optional-dependencies"][extra]]
    return reqs


def test_lock_covers_every_extra_the_project_declares():
    declared_extras = set(PYPROJECT["project"]["optional-dependencies"])
    assert set(PYPROJECT["tool"]["pip-tools"]["extra"]) == declared_extras, \
        "add the new extra to [tool.pip-tools] extra and run pip-compile"
    header = LOCK_TEXT.split("\n\n", 1)[0] if "\n\n" in LOCK_TEXT else LOCK_TEXT[:2000]
    for extra in declared_extras:
        assert f"--extra={extra}" in header, f"constraints.txt was not made with the extra {extra!r}: run pip-compile"


def test_every_declared_dependency_is_pinned_within_its_range():
    pins = locked()
    problems = []
    for req in declared():
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        name = canonicalize_name(req.name)
        if name not in pins:
            problems.append(f"{req.name} is declared in pyproject.toml but not in constraints.txt")
        elif not req.specifier.contains(pins[name], prereleases=True):
            problems.append(f"{req.name}: pyproject.toml asks {req.specifier}, constraints.txt pins {pins[name]}")
    assert not problems, "run pip-compile to refresh the lock:\n" + "\n".join(problems)


def test_the_lock_pins_nothing_twice_and_has_no_extras():
    names = [canonicalize_name(line.split("==", 1)[0]) for line in LOCK_TEXT.splitlines()
             if "==" in line and not line.lstrip().startswith("#")]
    assert len(names) == len(set(names))
    # pip refuses extras in a constraints file ("Constraints cannot have extras").
    assert not re.search(r"^[A-Za-z0-9._-]+\[", LOCK_TEXT, flags=re.M)


def test_the_environment_was_installed_from_the_lock():
    """Every locked package that is installed has the locked version (the README's commands and
    .ci/run install with ``-c constraints.txt``). A mismatch means this environment was set up
    another way, and the suite may be testing versions nobody locked."""
    pins = locked()
    wrong = []
    for name, version in pins.items():
        try:
            installed = Version(metadata.version(name))
        except metadata.PackageNotFoundError:
            continue
        if installed != version:
            wrong.append(f"{name} {installed} installed, {version} locked")
    if wrong:
        pytest.fail("the environment does not follow constraints.txt (install with "
                    "`python -m pip install -c constraints.txt -e '.[test]'`):\n" + "\n".join(wrong))


def test_the_install_commands_use_the_lock():
    """The README's two commands, ``.ci/run`` and the container image install with the lock."""
    readme = (ROOT / "README.md").read_text()
    commands = [line.strip() for line in readme.splitlines() if "pip install" in line and "-e " in line]
    assert len(commands) >= 2, "the README gives the two install commands"
    for command in commands:
        assert "-c constraints.txt" in command, command
    ci = (ROOT / ".ci" / "run").read_text()
    assert "-c constraints.txt" in ci
    test_command = next(c for c in commands if "pytest" in c)
    assert test_command in ci, "CI runs the README's test command verbatim"
    dockerfile = (ROOT / "deploy" / "Dockerfile").read_text()
    copies = [line for line in dockerfile.splitlines() if line.startswith("COPY ")]
    assert any("constraints.txt" in line.split() for line in copies), copies
    assert "pip install -c constraints.txt ." in dockerfile

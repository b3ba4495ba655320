"""Task packages (evaluator/packages.py): named in a suite, imported by the evaluator, their
versions pinned into the suite's hash and recorded in each result's provenance."""

from __future__ import annotations

import sys
import uuid
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest
import yaml

from evaluator import packages
from evaluator.packages import TaskPackageError
from evaluator.plan import build_plan
from evaluator.suite import Suite, SuiteError, load_suite
from testkit.factories import SUITE

PACKAGES_DIR = Path(__file__).resolve().parents[1] / "data" / "task_packages"
PACKAGED_SUITE = PACKAGES_DIR / "suite.yaml"


def suite_with(**fields: Any) -> Suite:
    return Suite.model_validate({**yaml.safe_load(SUITE.read_text()), **fields})


@pytest.fixture
def module_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def plain_package(root: Path, body: str = "") -> str:
    """A new package under `root` (a fresh name: imports and versions are cached by name)."""
    name = f"tasks_{uuid.uuid4().hex[:12]}"
    (root / name).mkdir()
    (root / name / "__init__.py").write_text(body)
    return name


@pytest.mark.parametrize("name", ["my-lab", "1tasks", "lab.class", "lab..tasks", ""])
def test_a_package_that_is_no_module_name_is_refused_with_what_a_name_is(name: str) -> None:
    with pytest.raises(ValueError, match="not a module name as `import` takes it"):
        suite_with(packages=[name])


def test_versions_must_name_exactly_the_packages() -> None:
    with pytest.raises(ValueError, match="a version for every package and nothing else"):
        suite_with(packages=["a", "b"], package_versions={"a": "1.0"})


def test_a_suite_without_packages_keeps_its_hash_and_pinned_versions_change_it() -> None:
    plain = suite_with()
    assert suite_with(packages=[]).sha256() == plain.sha256()
    named = suite_with(packages=["lab_tasks"])
    one = suite_with(packages=["lab_tasks"], package_versions={"lab_tasks": "1.0"})
    two = suite_with(packages=["lab_tasks"], package_versions={"lab_tasks": "1.1"})
    assert len({plain.sha256(), named.sha256(), one.sha256(), two.sha256()}) == 4


def test_the_plan_carries_each_package_with_its_pinned_version() -> None:
    suite = suite_with(
        packages=["b_tasks", "a_tasks"], package_versions={"a_tasks": "1", "b_tasks": "2"}
    )
    plan = build_plan(suite, "dev")
    assert list(plan.packages.items()) == [("b_tasks", "2"), ("a_tasks", "1")]  # import order
    assert build_plan(suite_with(packages=["c_tasks"]), "dev").packages == {"c_tasks": None}
    assert build_plan(suite_with(), "dev").packages == {}


def test_a_missing_package_says_which_and_how_to_install_it() -> None:
    with pytest.raises(TaskPackageError) as caught:
        packages.import_package("no_such_lab_tasks")
    message = str(caught.value)
    assert "'no_such_lab_tasks' is not installed" in message
    assert f"{sys.executable} -m pip install" in message
    assert "PYTHONPATH" in message


def test_a_package_that_fails_to_import_says_why(module_dir: Path) -> None:
    name = plain_package(module_dir, "import no_such_dependency_of_theirs\n")
    with pytest.raises(TaskPackageError, match=f"'{name}' failed to import: No module named"):
        packages.import_package(name)
    broken = plain_package(module_dir, "raise RuntimeError('bad asset path')\n")
    with pytest.raises(TaskPackageError, match="RuntimeError: bad asset path"):
        packages.import_package(broken)


def test_a_plain_module_is_versioned_by_a_hash_of_its_files(module_dir: Path) -> None:
    name = plain_package(module_dir, "X = 1\n")
    (module_dir / name / "asset.urdf").write_text("<robot/>")
    first = packages.source_hash(name)
    assert packages.installed_version(name) == f"src:{first}"
    (module_dir / name / "__pycache__").mkdir()
    (module_dir / name / "__pycache__" / "x.pyc").write_bytes(b"compiled")
    assert packages.source_hash(name) == first  # bytecode is no source
    (module_dir / name / "asset.urdf").write_text("<robot name='other'/>")
    assert packages.source_hash(name) != first  # an asset is part of the task


def test_an_installed_distribution_is_versioned_by_its_metadata() -> None:
    assert packages.installed_version("yaml") == metadata.version("PyYAML")


def test_the_evaluator_refuses_a_package_of_another_version(module_dir: Path) -> None:
    name = plain_package(module_dir)
    installed = packages.installed_version(name)
    assert packages.import_packages({name: installed}) == {name: installed}
    assert packages.import_packages({name: None}) == {name: installed}
    with pytest.raises(TaskPackageError, match="the suite was loaded with src:0000"):
        packages.import_packages({name: "src:0000"})


def test_without_maniskill_the_versions_must_be_stated(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(packages, "simulator_installed", lambda: False)
    with pytest.raises(TaskPackageError, match="state their versions in the suite's"):
        packages.pin(suite_with(packages=["lab_tasks"]))
    stated = suite_with(packages=["lab_tasks"], package_versions={"lab_tasks": "1.0"})
    assert packages.pin(stated) == (stated, None)
    assert packages.pin(suite_with()) == (suite_with(), None)


@pytest.mark.sim
def test_loading_pins_the_packages_and_names_who_registers_each_task(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.syspath_prepend(str(PACKAGES_DIR))
    suite = load_suite(PACKAGED_SUITE)
    both = Suite.model_validate(
        {
            **suite.model_dump(),
            "tasks": [
                *suite.model_dump()["tasks"],
                {"env_id": "PickCube-v1", "max_episode_steps": 5},
            ],
        }
    )
    pinned, resolution = packages.pin(both)
    assert resolution is not None
    version = packages.installed_version("manieval_test_tasks")
    assert version.startswith("src:")
    assert pinned.package_versions == {"manieval_test_tasks": version}
    assert resolution.providers == {
        "KeepCubeInRing-v1": "manieval_test_tasks",
        "PickCube-v1": "mani_skill",
    }
    assert pinned.sha256() != both.sha256()
    with pytest.raises(TaskPackageError, match=r"the suite states 0\.9"):
        packages.pin(both.model_copy(update={"package_versions": {"manieval_test_tasks": "0.9"}}))


@pytest.mark.sim
def test_a_task_no_package_registers_is_refused_with_those_it_registers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.syspath_prepend(str(PACKAGES_DIR))
    raw = yaml.safe_load(PACKAGED_SUITE.read_text())
    raw["tasks"][0]["env_id"] = "KeepCubeInRings-v1"
    with pytest.raises(SuiteError) as caught:
        packages.pin(Suite.model_validate(raw))
    assert "'KeepCubeInRings-v1' is registered neither by ManiSkill nor" in str(caught.value)
    assert "registered by them: KeepCubeInRing-v1" in str(caught.value)
